"""Which keyframes to match, chosen from their prior poses (pure math, no I/O).

Matching every pair grows quadratically and most pairs of a dive share nothing;
COLMAP's sequential matcher adds quadratic offsets (1, 2, 4, ... 512) that waste
a fifth to a third of the pairs on video, and its spatial matcher ignores z by
default. Here each keyframe gets at most

- `sequential_neighbours` successors in its own session (offsets 1..n, in time),
- `spatial_neighbours` partners whose *viewed point* (camera centre plus
  `view_distance_m` along the optical axis, x, y and z alike) lies within
  `spatial_radius_m` and whose optical axes differ by at most
  `max_view_angle_deg`: across sessions these are the spatial pairs, within a
  session (beyond the sequential window and `loop_min_separation_s` apart) the
  loop candidates,

so the pair count is at most N * (sequential + spatial): linear in N. Sessions
whose world pose is unknown get `bridging_pairs` against the placed ones, an
evenly spread sample bounded by `max_bridging_pairs`. The merge stage's
cross-session place pairs (keyframes of two dives it verified as filming the same
structure, `MergeFolder.read_place_pairs`) are matched too (`place_pairs`), so the
final adjustment ties the dives together exactly where the merge found them to
overlap, whatever the priors say.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from postproc.sfm.options import PairOptions as PairOptions
from shared.clock import ns_from_seconds

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Pair kinds, as stored in `PairSet.kind`.
SEQUENTIAL, SPATIAL, LOOP, BRIDGING, PLACE = 0, 1, 2, 3, 4
KIND_NAMES = ("sequential", "spatial", "loop", "bridging", "place")


@dataclass
class PairSet:
    """Image pairs (M, 2) with i < j (indices into the keyframe list) and their kind (M,)."""

    pairs: IntArray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    kind: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.pairs.shape[0])

    def counts(self) -> dict[str, int]:
        """Number of pairs of each kind, by name."""
        return {name: int(np.sum(self.kind == k)) for k, name in enumerate(KIND_NAMES)}


def _pack(rows: list[tuple[int, int, int]]) -> PairSet:
    """Deduplicate (i, j, kind) rows with i != j; the first kind listed for a pair wins."""
    if not rows:
        return PairSet()
    data = np.asarray(rows, dtype=np.int64)
    lo = np.minimum(data[:, 0], data[:, 1])
    hi = np.maximum(data[:, 0], data[:, 1])
    keep = lo != hi
    lo, hi, kind = lo[keep], hi[keep], data[keep, 2]
    _, first = np.unique(np.column_stack((lo, hi)), axis=0, return_index=True)
    first.sort()
    pairs = np.column_stack((lo[first], hi[first]))
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return PairSet(pairs=pairs[order], kind=kind[first][order])


def sequential_pairs(session: IntArray, stamps_ns: IntArray, neighbours: int) -> PairSet:
    """Each keyframe with its next `neighbours` keyframes in time in the same session."""
    session = np.asarray(session, dtype=np.int64)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    rows: list[tuple[int, int, int]] = []
    for s in np.unique(session):
        members = np.flatnonzero(session == s)
        members = members[np.argsort(stamps[members], kind="stable")]
        for offset in range(1, neighbours + 1):
            for a, b in zip(members[:-offset].tolist(), members[offset:].tolist(), strict=True):
                rows.append((a, b, SEQUENTIAL))
    return _pack(rows)


def viewed_points(world_from_cam: FloatArray, view_distance_m: float) -> FloatArray:
    """Points `view_distance_m` in front of each camera along its optical axis (N, 3), metres."""
    poses = np.asarray(world_from_cam, dtype=np.float64)
    return poses[:, :3, 3] + view_distance_m * poses[:, :3, 2]


def spatial_pairs(
    world_from_cam: FloatArray,
    session: IntArray,
    stamps_ns: IntArray,
    options: PairOptions,
    *,
    active: npt.NDArray[np.bool_] | None = None,
) -> PairSet:
    """Spatial (other session) and loop (same session, beyond the sequential window) pairs.

    Only keyframes with `active` true take part (default: all); poses must share one
    frame. Each keyframe keeps its `spatial_neighbours` nearest viewed points within
    `spatial_radius_m` whose optical axes are within `max_view_angle_deg`.
    """
    from scipy.spatial import cKDTree

    poses = np.asarray(world_from_cam, dtype=np.float64)
    session = np.asarray(session, dtype=np.int64)
    n = poses.shape[0]
    members = np.arange(n) if active is None else np.flatnonzero(active)
    if options.spatial_neighbours == 0 or members.size < 2:
        return PairSet()
    # Rank of each keyframe in its session's time order, to skip the sequential window.
    rank = np.zeros(n, dtype=np.int64)
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    for s in np.unique(session):
        idx = np.flatnonzero(session == s)
        rank[idx[np.argsort(stamps[idx], kind="stable")]] = np.arange(idx.size)
    points = viewed_points(poses[members], options.view_distance_m)
    axes = poses[members, :3, 2]
    tree = cKDTree(points)
    # Ask for more than needed: some neighbours fail the angle or sequential tests.
    k = min(members.size, 4 * options.spatial_neighbours + options.sequential_neighbours + 1)
    distances, neighbours = tree.query(points, k=k, distance_upper_bound=options.spatial_radius_m)
    min_cos = np.cos(np.deg2rad(options.max_view_angle_deg))
    min_separation_ns = ns_from_seconds(options.loop_min_separation_s)
    rows: list[tuple[int, int, int]] = []
    for a in range(members.size):
        i = int(members[a])
        kept = 0
        for d, b in zip(distances[a], neighbours[a], strict=True):
            if not np.isfinite(d) or b == a or b >= members.size:
                continue
            j = int(members[b])
            same = session[i] == session[j]
            if same and (
                abs(int(rank[i]) - int(rank[j])) <= options.sequential_neighbours
                or abs(int(stamps[i]) - int(stamps[j])) < min_separation_ns
            ):
                continue
            if float(axes[a] @ axes[b]) < min_cos:
                continue
            rows.append((i, j, LOOP if same else SPATIAL))
            kept += 1
            if kept >= options.spatial_neighbours:
                break
    return _pack(rows)


def bridging_pairs(unplaced: IntArray, placed: IntArray, max_pairs: int) -> PairSet:
    """An evenly spread sample of (unplaced, placed) pairs, at most `max_pairs`.

    For a session with no known world pose: its keyframes are matched against the
    placed keyframes on a grid of about sqrt(max_pairs) by sqrt(max_pairs) samples
    (each side capped at its size), so some pairs see the same part of the wreck if
    the session overlaps at all.
    """
    u = np.asarray(unplaced, dtype=np.int64)
    p = np.asarray(placed, dtype=np.int64)
    if u.size == 0 or p.size == 0 or max_pairs <= 0:
        return PairSet()
    side = max(int(np.sqrt(max_pairs)), 1)
    n_u = min(u.size, side)
    n_p = min(p.size, max(max_pairs // n_u, 1))
    pick_u = u[np.unique(np.linspace(0, u.size - 1, n_u).round().astype(np.int64))]
    pick_p = p[np.unique(np.linspace(0, p.size - 1, n_p).round().astype(np.int64))]
    rows = [(int(a), int(b), BRIDGING) for a in pick_u for b in pick_p]
    return _pack(rows)


def place_pairs(
    session: IntArray,
    stamps_ns: IntArray,
    session_names: Sequence[str],
    links: Sequence[tuple[str, int, str, int]],
) -> PairSet:
    """The merge's verified cross-session places as pairs of keyframe indices.

    session: session index (N,) of each keyframe, into `session_names`; stamps_ns
    (N,) int64. links: (session a, stamp a ns, session b, stamp b ns) per place the
    merge verified. Links to keyframes not in the list are skipped.
    """
    where = {
        (session_names[int(s)], int(t)): i
        for i, (s, t) in enumerate(zip(np.asarray(session), np.asarray(stamps_ns), strict=True))
    }
    rows = []
    for name_a, stamp_a, name_b, stamp_b in links:
        i = where.get((name_a, int(stamp_a)))
        j = where.get((name_b, int(stamp_b)))
        if i is not None and j is not None:
            rows.append((i, j, PLACE))
    return _pack(rows)


def merge_pair_sets(*sets: PairSet) -> PairSet:
    """Union of pair sets; a pair listed twice keeps the kind of its first set."""
    rows: list[tuple[int, int, int]] = []
    for s in sets:
        rows.extend((int(i), int(j), int(k)) for (i, j), k in zip(s.pairs, s.kind, strict=True))
    return _pack(rows)


def select_pairs(
    world_from_cam: FloatArray,
    session: IntArray,
    stamps_ns: IntArray,
    placed: npt.NDArray[np.bool_],
    options: PairOptions,
    *,
    places: PairSet | None = None,
) -> PairSet:
    """All pairs to match: sequential, spatial/loop among placed keyframes, bridging,
    and the merge's cross-session places (`place_pairs`) when given.

    world_from_cam: prior poses (N, 4, 4), `T_W_C` for placed keyframes (`T_S_C` for
    the others, used only for their loop candidates). session: session index (N,).
    stamps_ns: int64 ns (N,). placed: whether each keyframe's session is in W (N,).
    """
    poses = np.asarray(world_from_cam, dtype=np.float64)
    session = np.asarray(session, dtype=np.int64)
    placed = np.asarray(placed, dtype=bool)
    sets = [sequential_pairs(session, stamps_ns, options.sequential_neighbours)]
    if places is not None:
        sets.append(places)
    sets.append(spatial_pairs(poses, session, stamps_ns, options, active=placed))
    for s in np.unique(session[~placed]):
        # Loop candidates inside an unplaced session: its own frame is consistent.
        mask = session == s
        sets.append(spatial_pairs(poses, session, stamps_ns, options, active=mask))
        sets.append(
            bridging_pairs(np.flatnonzero(mask), np.flatnonzero(placed), options.max_bridging_pairs)
        )
    return merge_pair_sets(*sets)
