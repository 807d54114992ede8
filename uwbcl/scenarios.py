"""The paper's simulation scenarios (Tables 1 and 4) as data, and their passes.

Roadway frame OXYZ: X along the panel (retreat), Y across (towards the rig), Z up. The rig (the rail's centre
at height 0) sits at `rig_positions_m[cycle]` in the roadway frame with its axes parallel to OXYZ, so a target
at roadway position M is at M - rig in the radar frame, and the advance between cycles is
rig' - rig = -(P' - P).
"""

from __future__ import annotations

import dataclasses
import datetime as dt

import numpy as np

from . import geometry as geo
from .model import PassGeometry, RadarParameters, ScanPass
from .simulate import simulate_pass


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    targets_roadway_m: np.ndarray  # (M, 3)
    target_names: tuple[str, ...]
    reference_target: int  # index of the scene centre T
    rig_positions_m: np.ndarray  # (cycles, 3), roadway frame
    heights_m: tuple[float, ...]
    speed_m_s: float
    aperture_length_m: float
    radar: RadarParameters = dataclasses.field(default_factory=RadarParameters)
    paper_rotation_table_deg: tuple[float, ...] = ()  # as printed in the paper, for comparison

    def targets_radar_m(self, cycle: int) -> np.ndarray:
        return self.targets_roadway_m - self.rig_positions_m[cycle]

    def reference_point_m(self, cycle: int) -> np.ndarray:
        return self.targets_radar_m(cycle)[self.reference_target]

    def rotation_table_angle_deg(self, cycle: int) -> float:
        """The rig steers the table so the reference target is on boresight (tan theta_h = x_T / W)."""
        return geo.rotation_table_angle_for(self.reference_point_m(cycle), 0.0)

    def advance_m(self, cycle: int) -> np.ndarray:
        """True Delta P from cycle - 1 to cycle."""
        return self.rig_positions_m[cycle] - self.rig_positions_m[cycle - 1]

    def simulate(self, *, snr_db: float | None = None, speed_jitter: float = 0.0, seed: int = 0,
                 heights_m=None, rig_id: str = "sim-rig") -> list[ScanPass]:
        """Every pass of every cycle, deterministic under `seed`."""
        rng = np.random.default_rng(seed)
        heights = self.heights_m if heights_m is None else tuple(heights_m)
        start = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.timezone.utc)
        passes = []
        for cycle in range(len(self.rig_positions_m)):
            targets = self.targets_radar_m(cycle)
            for i, h in enumerate(heights):
                g = PassGeometry(height_m=h, rotation_table_angle_deg=self.rotation_table_angle_deg(cycle),
                                 reference_point_m=tuple(float(c) for c in self.reference_point_m(cycle)))
                when = start + dt.timedelta(minutes=45 * cycle, seconds=30 * i)
                passes.append(simulate_pass(
                    self.radar, g, targets, aperture_length_m=self.aperture_length_m,
                    speed_m_s=self.speed_m_s, snr_db=snr_db, speed_jitter=speed_jitter, rng=rng,
                    rig_id=rig_id, cycle=cycle,
                    pass_start_time=when.strftime("%Y-%m-%dT%H:%M:%SZ")))
        return passes


PAPER_SIM1 = Scenario(
    name="paper-sim1",
    targets_roadway_m=np.array([[0.786, 0.0, 0.300], [1.386, 0.0, 0.300], [1.986, 0.0, 0.300]]),
    target_names=("A", "B", "C"),
    reference_target=1,
    rig_positions_m=np.array([[0.0, 2.4, 0.0], [0.8, 2.5, 0.0]]),
    heights_m=(0.15, 0.30),
    speed_m_s=0.15,
    aperture_length_m=2.0,
    paper_rotation_table_deg=(30.0, 13.18),
)

PAPER_SIM2 = Scenario(
    name="paper-sim2",
    targets_roadway_m=np.array([[1.678, 0.0, 0.400], [1.678, 0.0, 1.200], [1.678, 0.0, 1.600]]),
    target_names=("D", "E", "F"),
    reference_target=1,
    rig_positions_m=np.array([[0.0, 2.0, 0.0], [0.7, 1.9, 0.0]]),
    heights_m=(0.05, 0.25),
    speed_m_s=0.2,
    aperture_length_m=1.8,
    paper_rotation_table_deg=(40.0, 27.24),
)

SCENARIOS = {s.name: s for s in (PAPER_SIM1, PAPER_SIM2)}
