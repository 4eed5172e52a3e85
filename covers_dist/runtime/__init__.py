"""The distributed runtime: rollout workers, the clustering service, learners and the driver.

Plain classes live in ``rollout.py``, ``clustering_service.py`` and ``learner.py``; they become Ray
actors only in ``actors.py``. ``driver.py`` runs Algorithm 1 on either backend (``backends.py``).
"""
