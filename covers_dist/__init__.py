"""covers-dist: COVERS (continual vision-based RL with group symmetries) as a distributed service."""

__version__ = "0.1.0"
