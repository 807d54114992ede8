"""Coherent registration of two cycles' rib images at a candidate translation: association evidence that the
plates' positions lack (docs/method.md section 6.4).

Plates on a regular grid look alike: a translation one plate spacing off can match as many plates as the
right one. Their phases do not: each plate's sub-wavelength position, and the rib's own scatterers around it,
line up in both cycles at the right translation only. So, at each rail height both cycles have, cycle b's pass
is backprojected at a lattice of points of its rib (x along the rail, R_c across, over the range band of its
located plates), cycle a's pass at the same points moved by the candidate translation t (P_a = P_b + t, the
rig frame), and the product I_b conj(I_a(t)) is summed over tiles of about a plate response's size (TILE_M),
c_k. At a wrong
translation the tiles' phases are unrelated, and

    Q = |sum_k c_k|^2 / sum_k |c_k|^2                                                                 (R1)

is about exponential with mean 1 (the coherence test of n independent looks); at the right one the phases
agree and Q approaches N = (sum |c_k|)^2 / sum |c_k|^2, the number of tiles that carry the images' energy.
Against a vague alternative (Q anywhere in [0, N]) the log-likelihood ratio of a translation is

    E_h(t) = Q - ln N                                                                                (R2)

small for one plate alone (N <= 4: a plate matched to another plate is as coherent as to itself), large when
several plates and the rib agree. The candidate's vertical is searched within its uncertainty (eq. R3,
`evidence`) and the heights, independent looks, add up (eq. R4, `RibRegistration.scorer`). The association
adds E to the scores of competing translations (eq. M7), never against "no plate in common": E's tail under a
wrong translation is known only from simulated ribs, and what dust, spalling or moving mesh between cycles do
to it only real recordings can tell, so it only chooses between translations the plates already support.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from collections.abc import Callable, Hashable

import numpy as np

from .archive import height_mm
from .detect.phase import PointEcho
from .focus.protocol import Focuser
from .focus.reference import NUMPY_FOCUSER
from .model import ScanPass
from .records import CycleResult

LATTICE_M = (0.01, 0.02)  # rib points along the rail and in R_c (resolution ~2 cm along, ~9 cm in range)
TILE_M = (0.10, 0.10)  # the tiles of eq. R1: about one plate's response, so one scatterer is one look or few
BAND_MARGIN_M = 0.15  # the rib band: the located plates' R_c range widened by this on both sides
# Points x pulses of one lattice's backprojection beyond which a pair gets no evidence (~1 s in numpy; the
# study's are ~3e6): a band spread by stray plates or a very long rail must not stall the batch.
MAX_LATTICE_WORK = 50_000_000
Z_SEARCH_MAX_M = 0.15  # eq. R3 searches the candidate's vertical over +-3 sigma, never wider than this


def coherence(ib: np.ndarray, ia: np.ndarray) -> float:
    """|sum ib conj(ia)| / sqrt(sum |ib|^2 sum |ia|^2), 0 when either is empty (a diagnostic, not scored)."""
    den = math.sqrt(float(np.sum(np.abs(ib) ** 2)) * float(np.sum(np.abs(ia) ** 2)))
    return float(np.abs(np.sum(ib * np.conj(ia)))) / den if den > 0 else 0.0


def tile_sums(product: np.ndarray, tile: tuple[int, int]) -> np.ndarray:
    """c_k of eq. R1: the (nx, nr) product summed over tiles of tile = (lattice steps along, across); the
    last partial tiles are kept. Flat."""
    tx, tr = tile
    nx, nr = product.shape
    padded = np.zeros((-(-nx // tx) * tx, -(-nr // tr) * tr), dtype=product.dtype)
    padded[:nx, :nr] = product
    return padded.reshape(padded.shape[0] // tx, tx, padded.shape[1] // tr, tr).sum(axis=(1, 3)).ravel()


def evidence(ib: np.ndarray, ia: np.ndarray, tile: tuple[int, int], phase_per_m: np.ndarray | None = None,
             sigma_z_m: float = 0.0) -> float:
    """Eq. R2: E = Q - ln N of two images on the same (nx, nr) lattice (eq. R1 for Q and N); 0 when either
    is empty.

    Eq. R3: the candidate's vertical is the plates' estimate, often centimetres off (two heights close
    together, a far rib), and a vertical error dz moves a's rib points in range by an amount that grows with
    their height, so the product's phase drifts across the band by phase_per_m (nr,) x dz (rad). E is the
    best over dz within +-3 sigma_z_m (at most Z_SEARCH_MAX_M), less ln K for the K independent verticals
    tried (K: the search's span over the dz that turns the phase across the band by pi)."""
    product = ib * np.conj(ia)
    trials, k_eff = [0.0], 1.0
    if phase_per_m is not None and sigma_z_m > 0:
        spread = float(np.ptp(phase_per_m))
        span = min(3.0 * sigma_z_m, Z_SEARCH_MAX_M)
        if spread > 0:
            decorrelation = math.pi / spread  # dz (m) that turns the phase across the band by pi
            k_eff = max(1.0, 2.0 * span / decorrelation)
            trials = np.linspace(-span, span, 2 * int(math.ceil(4.0 * span / decorrelation)) + 1)
    best = -math.inf
    for dz in trials:
        c = tile_sums(product if dz == 0.0 else product * np.exp(-1j * dz * phase_per_m)[None, :], tile)
        power = float(np.sum(np.abs(c) ** 2))
        if not power > 0:
            return 0.0
        q = float(np.abs(np.sum(c)) ** 2) / power
        n = float(np.sum(np.abs(c))) ** 2 / power
        best = max(best, q - math.log(n))
    return best - math.log(k_eff)


@dataclasses.dataclass(frozen=True)
class RibLattice:
    """Cycle b's rib points and its image there."""

    x_m: np.ndarray  # (nx,) along the rail, LATTICE_M[0] apart
    rc_m: np.ndarray  # (nr,) closest-approach range at b's height, LATTICE_M[1] apart
    y_m: float  # the rib's Y (the median located plate's), signed
    dz_m: np.ndarray  # (nr,) z - h_b of each range on the rib plane (on the plates' side of the rail)
    height_m: float  # h_b
    image: np.ndarray  # (nx, nr) complex


def rib_lattice(echo: PointEcho, plates_m: np.ndarray) -> RibLattice | None:
    """Cycle b's lattice over the R_c band of its located plates (n, 3) and its pass's imaged extent; None
    without plates, or when its backprojection would exceed MAX_LATTICE_WORK (no evidence, bounded time)."""
    plates_m = np.asarray(plates_m, dtype=float).reshape(-1, 3)
    if len(plates_m) == 0 or not np.all(np.isfinite(plates_m)):
        return None
    h = echo.height_m
    y = float(np.median(plates_m[:, 1]))
    rc_plates = np.hypot(plates_m[:, 1], plates_m[:, 2] - h)
    lo = max(float(rc_plates.min()) - BAND_MARGIN_M, abs(y))
    r = np.arange(lo, float(rc_plates.max()) + BAND_MARGIN_M + 1e-9, LATTICE_M[1])
    x0, x1 = echo.x_span_m(float(np.median(r)))
    x = np.arange(x0, x1 + 1e-9, LATTICE_M[0])
    if x.size * r.size * echo.rc.data.shape[0] > MAX_LATTICE_WORK:
        return None
    side = 1.0 if np.median(plates_m[:, 2] - h) >= 0 else -1.0
    dz = side * np.sqrt(np.maximum(r**2 - y**2, 0.0))
    return RibLattice(x, r, y, dz, h, echo.image(x[:, None], r[None, :]))


def moved_image(lat: RibLattice, echo_a: PointEcho, t_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cycle a's image at b's rib points moved by t (3,) (x + t_x, R_c on the rib plane from a's height), and
    the phase per metre of vertical error at each range (nr,) (eq. R3): the carrier's k cos(squint) times
    dR_c / dt_z."""
    t = np.asarray(t_m, dtype=float)
    dz = lat.dz_m + lat.height_m - echo_a.height_m + t[2]
    r_a = np.hypot(lat.y_m + t[1], dz)
    k = echo_a.grid.two_way_wavenumber_rad_m * echo_a.grid.cos_squint
    return echo_a.image(lat.x_m[:, None] + t[0], r_a[None, :]), k * dz / np.maximum(r_a, 1e-9)


def tile_steps() -> tuple[int, int]:
    """TILE_M in lattice steps."""
    return tuple(max(1, int(round(t / d))) for t, d in zip(TILE_M, LATTICE_M))


class RibRegistration:
    """The evidence (eqs. R2-R4) of candidate translations between two cycles of a rig.

    `load(cycle, height_mm)` returns the cycle's pass at that rail height (mm, `archive.height_mm`) or None
    when it cannot be read. The echoes of the last few cycles are kept (a few MB each), and b's lattices and
    the scores of recent pairs, so the chain's repeated measurements of a pair cost nothing twice.
    Deterministic: the same passes, the same evidence.
    """

    def __init__(self, load: Callable[[CycleResult, int], ScanPass | None], focuser: Focuser = NUMPY_FOCUSER,
                 capacity: int = 24, max_echo_bytes: int = 256 << 20, max_scores: int = 4096):
        self._load = load
        self._focuser = focuser  # what backprojects the lattices (`Focuser.backproject_track_points`)
        self._capacity = capacity  # passes (a few cycles of 2-4 heights) kept, their echoes within the bytes
        self._max_echo_bytes = max_echo_bytes
        self._max_scores = max_scores
        self._echoes: OrderedDict[Hashable, PointEcho | None] = OrderedDict()
        self._lattices: OrderedDict[Hashable, RibLattice | None] = OrderedDict()
        self._scores: OrderedDict[Hashable, float] = OrderedDict()

    @staticmethod
    def _key(c: CycleResult) -> tuple[str, int]:
        return c.rig_id, c.cycle

    @staticmethod
    def _remember(cache: OrderedDict, key: Hashable, value, limit: int):
        cache[key] = value
        while len(cache) > limit:
            cache.popitem(last=False)
        return value

    def _echo(self, c: CycleResult, height_mm: int) -> PointEcho | None:
        key = (*self._key(c), height_mm)
        if key in self._echoes:
            self._echoes.move_to_end(key)
            return self._echoes[key]
        scan = self._load(c, height_mm)
        echo = self._remember(self._echoes, key, None if scan is None else PointEcho(scan, self._focuser),
                              self._capacity)
        # memory bounded whatever the passes' size: the oldest echoes go first, the two being compared stay
        while len(self._echoes) > 2 and sum(e.rc.data.nbytes for e in self._echoes.values()
                                            if e is not None) > self._max_echo_bytes:
            self._echoes.popitem(last=False)
        return echo

    def _lattice(self, b: CycleResult, height_mm: int) -> RibLattice | None:
        key = (*self._key(b), height_mm)
        if key in self._lattices:
            return self._lattices[key]
        echo = self._echo(b, height_mm)
        plates = np.array([p.position_m for p in b.plates], dtype=float).reshape(-1, 3)
        return self._remember(self._lattices, key, None if echo is None else rib_lattice(echo, plates),
                              self._capacity)

    def scorer(self, a: CycleResult, b: CycleResult) -> Callable[[np.ndarray, float], float]:
        """The evidence E(t) of a translation t (3,) m for a -> b whose vertical is uncertain by sigma_z_m:
        eq. R4, the sum of eqs. R2-R3 over the rail heights both cycles have (each height's pass is an
        independent look at the rib); 0 from a height whose pass cannot be read."""
        heights = sorted({height_mm(h) for h in a.heights_m} & {height_mm(h) for h in b.heights_m})

        def score(t_m: np.ndarray, sigma_z_m: float = 0.0) -> float:
            t = np.asarray(t_m, dtype=float)
            key = (self._key(a), self._key(b), tuple(heights), tuple(np.round(t * 1e4).astype(int)),
                   round(sigma_z_m * 1e4))
            if key in self._scores:
                return self._scores[key]
            value = 0.0
            for h in heights:
                lat = self._lattice(b, h)
                echo_a = None if lat is None else self._echo(a, h)
                if echo_a is not None:
                    image, phase_per_m = moved_image(lat, echo_a, t)
                    value += evidence(lat.image, image, tile_steps(), phase_per_m, sigma_z_m)  # eq. R4
            return self._remember(self._scores, key, value, self._max_scores)

        return score
