"""The ground station's two records: what the surveyor asked of a report (`ReportOptions`) and what one log's survey
computed (`Survey`), shared by the report's stages (the survey, its warnings, the writers) and by the tools and
tests that call them."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from firmware_py.core.config_file import SiteSection
from firmware_py.core.storage import Storage
from ground.base import FLOOR, Base, BaseSpec
from ground.building_check import SizeCheck
from ground.exports.formats import ExportFormat
from ground.floor_check import FloorLevel
from ground.metadata import SurveyInfo
from ground.piles import PileOptions
from ground.pointcloud import Cloud
from ground.pose_correction import PoseCorrection
from ground.pose_knots import PoseCorrectionOptions
from ground.rangefinder_height import RangefinderShare
from ground.self_calibration import KnownMount, MountEstimate
from ground.servo_timing import ServoTiming
from ground.smoothing import DEFAULT_CUBIC_LIMIT, DEFAULT_NODE_SLOPES, CubicLimit, NodeSlopes
from ground.surface import DEFAULT_CELL_M, DEFAULT_EMPTY_CELLS, DEFAULT_SURFACE_FIT, Grid, bridged_cells
from ground.uncertainty import ErrorTerms, SurveyErrors
from ground.volume_warnings import DEFAULT_MAX_INTERVAL_PCT

DEFAULT_MAX_GRID_MEMORY_BYTES = 2 * 1024**3
"""Default memory allowed for the grid: 2 GiB, 10.7 M cells (60 x 40 m down to 1.5 cm cells)."""


@dataclass(frozen=True)
class ReportOptions:
    """What the surveyor asked of a report (`pilescan-ground report`'s options and `--config`'s keys); the defaults
    are the report's own."""

    cell_m: float = DEFAULT_CELL_M
    empty_cells: str = DEFAULT_EMPTY_CELLS
    plots: bool = True
    truth_volume_m3: float | None = None
    surface_fit: str = DEFAULT_SURFACE_FIT  # ground.surface.SURFACE_FITS ("cubic" is the paper's)
    surface_slopes: NodeSlopes = DEFAULT_NODE_SLOPES  # local-linear: where its cubic's slopes come from (gp_slopes)
    surface_limit: CubicLimit = DEFAULT_CUBIC_LIMIT  # where the cubic leaves its triangle's range (CubicLimit)
    servo_retiming: bool = True  # re-estimate the servo's timing when the sweeps disagree (ground.servo_timing)
    despike: bool = True  # leave out isolated one-/two-sample range spikes (ground.despike; threshold from the header)
    max_grid_memory_bytes: int = DEFAULT_MAX_GRID_MEMORY_BYTES  # refuse a --cell whose grid would need more
    self_calibration: bool = True  # servo zero/scale and boresight from the floor and walls (ground.self_calibration)
    site: SiteSection | None = None  # [site] of a --config file: the log's building is checked against it
    max_interval_pct: float = DEFAULT_MAX_INTERVAL_PCT  # warn when the 90 % interval is wider than this
    base: BaseSpec = FLOOR  # the surface the volume is measured from (ground.base)
    piles: PileOptions = field(default_factory=PileOptions)  # names, densities, units (ground.piles)
    info: SurveyInfo = field(default_factory=SurveyInfo)  # site name, time zone, operator, aircraft (ground.metadata)
    exports: tuple[ExportFormat, ...] = ()  # standard exports to write beside the report (ground.exports)
    pose_correction: bool = True  # correct the trajectory from the building (ground.pose_correction): applied only
    # when significant; indoors the logged pose drifts (docs/pose_error.md)
    baro_walk_m_per_sqrt_s: float = PoseCorrectionOptions.vertical_walk_m_per_sqrt_s  # the altitude reference's
    # believed drift: how far a floor seen only away from the walls may move the height, and the level term's sigma
    storage: Storage | None = None  # the building in place of the log header's (--storage; None: the header's)
    lever_arm_m: tuple[float, float, float] | None = None  # the LiDAR's lever arm for the header's (--lever-arm)
    mount: KnownMount | None = None  # the mount as measured (--mount), applied in place of the self-calibration
    noise_corrections: bool = False  # the noisy surface's three bias corrections (survey_of_cloud); not yet default
    pointing_bias: bool = False  # points moved back along their beams by the pointing error's bias (pointing_bias)


@dataclass(frozen=True)
class Survey:
    """Everything computed from one log, for the report writers and for tests."""

    cloud: Cloud
    pile_points_w: np.ndarray
    grid: Grid
    heights_fit: np.ndarray
    heights: np.ndarray
    counts: np.ndarray
    storage: Storage
    n_cells_clipped: int = 0  # cells whose fit left the building (see surface.clip_to_building)
    sweep_disagreement_m: float | None = None  # ground.consistency: rising vs falling sweeps
    servo_timing: ServoTiming | None = None  # the re-estimated servo motion, when its model was wrong
    servo_retimed: bool = False  # the angles above are the re-estimated ones
    mount: MountEstimate | None = None  # self-calibration from the building (None: not run)
    implausible: dict[str, int] | None = None  # ground.plausibility: samples left out per broken limit
    despike_unavailable: str | None = None  # why despiking asked for could not run (ground.despike.why_no_threshold)
    errors: SurveyErrors | None = None  # the volume's error terms (ground.uncertainty); None: not estimated
    face_spread_m: float | None = None  # a cell's points spanning more height hold a face (ground.uncertainty)
    base: Base | None = None  # the surface the volume is measured from (ground.base); None: the floor z = 0
    own_terms: ErrorTerms | None = None  # the surface's own error terms (ErrorTerms) before a fitted floor rebased them
    errors_in: Callable[[np.ndarray], SurveyErrors] | None = None  # the error terms over a cell mask (one pile's)
    pose: PoseCorrection | None = None  # the trajectory's correction from the building (None: not run)
    rangefinder: RangefinderShare | None = None  # the rangefinder's share of the logged height (None: not run)
    building: tuple[SizeCheck, SizeCheck] | None = None  # its length and width as the sweeps measured them
    structure: np.ndarray | None = None  # the cloud's points taken as wall, roof or glitch (pointcloud.structure_mask)
    floor: FloorLevel | None = None  # the floor's level as the sweeps saw it (ground.floor_check; None: not seen)
    lever_arm_body_m: np.ndarray | None = None  # the lever arm the points were placed with (header's or --lever-arm's)
    heights_hull: np.ndarray | None = None  # the points' own fit over their hull, before `wall-strip` left the strip
    # cells its contacts contradict to the fill (ground.wall_strip); None: heights_fit is that fit
    edge_fit: np.ndarray | None = None  # the surfaced cells' heights with scipy's slopes, where the GP's slopes made
    # heights_fit: the unseen term's slope where sight stopped comes from them (ground.uncertainty.edge_heights_m)

    @cached_property
    def bridged(self) -> np.ndarray:
        """The fitted cells with no point within the seen radius (`ground.surface.bridged_cells`): made once for the
        report's `bridged_area_m2` and its coverage figure."""
        return bridged_cells(self.counts, np.isfinite(self.heights_fit), self.grid.cell_xy_m)
