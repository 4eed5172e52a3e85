"""Adapters that let other frameworks use covers-dist's components (imported on demand)."""
