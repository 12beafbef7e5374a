"""Result types returned by :meth:`beo_ros.core.bank.ModelBank.estimate`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UNKNOWN_LABEL = 'unknown'


@dataclass
class Hypothesis:
    """One (class, yaw) pose hypothesis; ``score`` is a pooled-grid log-likelihood (higher is
    better; the chosen class's hypotheses are scored with all its components, the other
    classes' with the leading ``pose_components`` (every class's with a given yaw or
    ``refine_deg`` 0: no refinement), so compare scores within one class only)."""

    label: str
    yaw: float
    score: float


@dataclass
class Estimate:
    """What the bank says about one observed object.

    Grid quantities are in the *observed* grid frame (axes x, y, z; z up; voxel centres at integer
    indices, rotation centre at ``(N-1)/2``).

    Attributes:
        label: best class name, or ``'unknown'`` when no class explains the object.
        scores: class name -> calibrated probability (sums to 1 over the classes).
        yaw: radians, right-handed rotation about +z that maps the canonical model onto the object.
        completion: float32 (N,N,N) occupancy probability in the observed grid's frame: 1 / 0
            where seen, calibrated for the unknown voxels when the bank has an
            ``occupancy_calibration`` (``beo_ros.core.calibration``).
        variance: float32 (N,N,N) predictive variance of the linear-Gaussian occupancy (0
            where seen). The model's own quantity, not a good uncertainty: on ModelNet10 views
            it ranks the wrong voxels little better than chance (see ``occupancy_variance``).
        hypotheses: top (class, yaw) hypotheses: ``(label, yaw)`` first (the best class's
            name when label is 'unknown'), then the chosen class's other yaw modes, then the
            other classes' best. When the orientation verifier turned the yaw by a quarter
            turn, the first one's score can be below the likelihood's own choice, which is
            listed next.
        symmetric_yaws: radians, the yaws that the completed shape cannot tell from ``yaw``:
            ``yaw`` + each quarter turn about +z that maps the completion (p >= 0.5) onto itself
            with IoU >= 0.9, turned about its footprint's centre (see
            :func:`beo_ros.core.grid.symmetric_turns`). Empty for a shape with no such turn;
            [yaw + pi] for a table that looks the same turned round. A hint: of the turns it
            lists on ModelNet10 views, 77 % are turns of the true object (fold 0).
        timings: seconds per stage ('pose_and_features', 'classify', 'pose_refinement',
            'orientation_check', 'completion', 'total'; 'outliers', 'voxelize' and, for a bank
            with a 'points' classifier, 'point_descriptors' from ``estimate_points``; only
            'total' for a grid with no occupied voxel).
        classifier_mode: the rule that decided the class: 'points' (the bank's classifier on
            the per-class log-likelihood + the raw points' side-normal descriptors),
            'complete' / 'partial' (the bank's classifier on the grid features),
            'max_likelihood' (no classifier for this case) or 'none' (the grid has no occupied
            voxel: label 'unknown', the class prior as scores, nothing completed).
        features: float64 (C, F) the classification features of every class (rows in class
            order, columns ``beo_ros.core.inference.FEATURE_NAMES``) at its stage-1 yaw (or the
            given one), or None (the grid has no occupied voxel).
        point_features: float64 (2,) side-normal descriptors (r4, frac10) of the raw points
            (see :mod:`beo_ros.core.normals`), or None (not computed: no points, or the bank
            has no 'points' classifier); NaN when undefined for this cloud.
        classifier_note: why the 'points' classifier was not used although the bank has one
            (e.g. its descriptors are undefined for a tiny cloud: the grid rule decided), why
            the class prior was not applied (a classifier without class counts), and / or
            that the grid has no occupied voxel (classifier_mode 'none'); else ''.
        grid: int8 (N,N,N) labelled input grid (1 occupied, 0 free, -1 unknown).
        pose: float64 (4,4) object frame in the input frame (only from ``estimate_points``): the
            translation is the object centre in metres (the middle of the completed points'
            extent along the object axes), the rotation the grid's axes (z up, x horizontal
            from the sensor towards the object) turned by ``yaw`` about up.
        heading_offset: radians (only from ``estimate_points``): ``yaw`` + heading_offset is
            the object's heading about up in the input frame, measured from the input x axis
            projected on the horizontal plane (the y axis if x is within 25° of up or down).
            ``yaw``, the hypotheses' and the symmetric yaws are in the grid frame, whose x axis
            follows the bearing from the sensor; add this to compare them across views.
        grid_to_input: float64 (4,4) maps homogeneous grid index coordinates to the input frame
            (only from ``estimate_points``).
        n_outliers: points removed as statistical outliers before the voxelization (only from
            ``estimate_points``; see :mod:`beo_ros.core.outliers`).
        n_off_cluster: points removed after them as outside the largest cluster (only from
            ``estimate_points`` with a ``cluster_tolerance``).
        n_outside_grid: points left after those that fell outside the grid (only from
            ``estimate_points``; a metric grid, or one placed by its ``center``): not
            voxelized, so the estimate is of the part inside (an object larger than the grid,
            or points not in metres).
        completed_points: float32 (m,3) centres of voxels with probability >= threshold, input frame
            (only from ``estimate_points``), and ``completed_probability`` float32 (m,).
        dimensions: float64 (3,) extent in metres of those voxels (outer faces) along the axes
            of ``pose`` (only from ``estimate_points``; zeros when none is completed): taken
            from float64 centres, as ``completed_points`` are centimetres off at 1e6 m.
    """

    label: str
    scores: dict
    yaw: float
    completion: np.ndarray
    variance: np.ndarray
    hypotheses: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    features: np.ndarray | None = None
    grid: np.ndarray | None = None
    pose: np.ndarray | None = None
    grid_to_input: np.ndarray | None = None
    completed_points: np.ndarray | None = None
    completed_probability: np.ndarray | None = None
    classifier_mode: str = ''
    point_features: np.ndarray | None = None
    classifier_note: str = ''
    symmetric_yaws: list = field(default_factory=list)   # last: positional use stays as it was
    heading_offset: float | None = None
    n_outliers: int = 0
    n_off_cluster: int = 0
    n_outside_grid: int = 0
    dimensions: np.ndarray | None = None

    @property
    def occupancy_variance(self) -> np.ndarray | None:
        """float32 (N,N,N) variance p (1 - p) of each 0/1 voxel under ``completion`` (0 where
        seen): the per-voxel uncertainty to use. With a calibrated completion it ranks the
        wrong voxels far better than ``variance`` (AUROC 0.85 against 0.63 on held-out
        ModelNet10 views, ``scripts/uncertainty.py``). None when ``completion`` is None."""
        if self.completion is None:
            return None
        p = np.asarray(self.completion, dtype=np.float32)
        return p * (1 - p)

    @property
    def probability(self) -> float:
        """Probability of ``label`` (0 for 'unknown')."""
        return float(self.scores.get(self.label, 0.0))
