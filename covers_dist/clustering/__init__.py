"""Policy assignment: distances between feature sets, the policy bank, assignment, metrics.

Plain Python (numpy, POT, scikit-learn; no torch, Ray or FastAPI): the clustering actor hosts a
:class:`PolicyBank`, serial code and tests call it directly. See docs/guide/clustering.md.
"""

from .assignment import DECISIONS, RULES, AssignmentRecord, decide, decide_calibrated
from .bank import MODES, PolicyBank
from .buffer import REPLACEMENT_RULES, ObservationBuffer
from .distances import DISTANCES, METRIC_NAMES, get_distance, mahalanobis, mean_euclidean, wasserstein1
from .features import FEATURE_NORMS, FeatureFn, SharedFeatures, color_histogram, normalize_pair
from .metrics import adjusted_rand_index, calibration_tail, confusion_table, policy_counts
from .persistence import FORMAT_VERSION, CheckpointError, load_bank, save_bank
from .policy_entry import PolicyEntry

__all__ = [
    "AssignmentRecord",
    "CheckpointError",
    "DECISIONS",
    "DISTANCES",
    "FEATURE_NORMS",
    "FORMAT_VERSION",
    "FeatureFn",
    "METRIC_NAMES",
    "MODES",
    "ObservationBuffer",
    "PolicyBank",
    "PolicyEntry",
    "REPLACEMENT_RULES",
    "RULES",
    "SharedFeatures",
    "adjusted_rand_index",
    "calibration_tail",
    "color_histogram",
    "confusion_table",
    "decide",
    "decide_calibrated",
    "get_distance",
    "load_bank",
    "mahalanobis",
    "mean_euclidean",
    "normalize_pair",
    "policy_counts",
    "save_bank",
    "wasserstein1",
]
