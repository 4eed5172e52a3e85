"""One router per resource: health, policies, assignments, metrics, actions."""

from . import actions, assignments, health, metrics, policies

__all__ = ["actions", "assignments", "health", "metrics", "policies"]
