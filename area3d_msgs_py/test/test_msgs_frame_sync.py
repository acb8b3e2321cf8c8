"""StampSync: parts of a frame pair by stamp (exact, or within a slop); orphans are dropped after
the age limit; the pairing rate says how many frames a lossy transport cost."""

import itertools
import random

import pytest

from area3d_msgs_py.errors import InputError
from area3d_msgs_py.frame_sync import MIN_GAPS, CameraInfoCache, HeldFrames, StampSync

S = 1_000_000_000


@pytest.mark.parametrize("slop_ns", [0, 5_000_000])
def test_a_frame_completes_when_every_stream_has_the_stamp_in_any_order(slop_ns):
    parts = {"color": "C", "depth": "D", "pose": "P"}
    for order in itertools.permutations(parts):
        sync = StampSync(("color", "depth", "pose"), slop_ns=slop_ns)
        results = [sync.add_part(key, 10 * S, parts[key]) for key in order]
        assert results[:2] == [None, None], order
        assert results[2] == (10 * S, parts), order
        assert all(sync.pending(k) == [] for k in parts), order


def test_with_a_slop_parts_a_few_milliseconds_apart_pair_with_the_closest_and_the_reference_stamp():
    ms = 1_000_000
    for order in itertools.permutations(("color", "depth", "pose")):
        sync = StampSync(("color", "depth", "pose"), slop_ns=10 * ms)
        stamps = {"color": 100 * ms, "depth": 104 * ms, "pose": 93 * ms}
        sync.add("depth", 125 * ms, "later depth")  # 25 ms off the colour: never its partner
        results = [sync.add_part(k, stamps[k], k) for k in order]
        assert results[-1] == (100 * ms, {"color": "color", "depth": "depth", "pose": "pose"})
        assert sync.pending("depth") == [125 * ms]
    # beyond the slop nothing pairs, and without one only identical stamps do
    sync = StampSync(("color", "depth"), slop_ns=10 * ms)
    sync.add("color", 100 * ms, "c")
    assert sync.add("depth", 111 * ms, "d") is None
    exact = StampSync(("color", "depth"))
    exact.add("color", 100 * ms, "c")
    assert exact.add("depth", 100 * ms + 1, "d") is None
    with pytest.raises(InputError, match="^slop_ns: "):
        StampSync(("a", "b"), slop_ns=-1)


def test_a_lost_part_costs_its_own_frame_only_and_the_pairing_rate_says_how_many():
    """A third of the parts lost on a best-effort link (30 Hz, depth stamped 3 ms after colour):
    every frame whose parts all arrived pairs, each lost part costs one frame, and the rate is
    the share of colour frames that paired."""
    ms = 1_000_000
    rng = random.Random(3)
    sync = StampSync(("color", "depth"), max_age_ns=200 * ms, slop_ns=10 * ms)
    whole, paired = 0, []
    for i in range(300):
        t = i * 33 * ms
        kept = {k: rng.random() > 1 / 3 for k in ("color", "depth")}
        whole += all(kept.values())
        if kept["color"]:
            paired.append(sync.add_part("color", t, i))
        if kept["depth"]:
            paired.append(sync.add_part("depth", t + 3 * ms, i))
    frames = [p for p in paired if p is not None]
    assert len(frames) == whole == sync.frames_paired
    assert all(f.parts["color"] == f.parts["depth"] for f in frames)
    rate = sync.pairing_rate()
    assert rate is not None and 0.55 < rate < 0.8  # about 2/3 of the colour frames
    assert sync.parts_dropped > 0


def test_different_stamps_never_pair():
    sync = StampSync(("color", "depth"))
    assert sync.add("color", 1 * S, "a") is None
    assert sync.add("depth", 1 * S + 1, "b") is None
    assert sync.pending("color") == [1 * S] and sync.pending("depth") == [1 * S + 1]


def test_interleaved_frames_each_pair_with_their_own_parts():
    sync = StampSync(("color", "depth"))
    sync.add("color", 1 * S, "c1")
    sync.add("color", 2 * S, "c2")
    assert sync.add("depth", 2 * S, "d2") == {"color": "c2", "depth": "d2"}
    assert sync.add("depth", 1 * S, "d1") == {"color": "c1", "depth": "d1"}


def test_orphans_older_than_the_age_limit_are_dropped_and_reported():
    sync = StampSync(("color", "depth", "pose"), max_age_ns=5 * S)
    sync.add("pose", 1 * S, "P")
    sync.add("color", 4 * S, "C")
    sync.add("depth", 7 * S, "D")
    assert sync.pop_dropped() == []  # a newer part alone is no reason to give up on older ones
    sync.add("color", 7 * S, "C7")
    assert sync.add("pose", 7 * S, "P7") is not None  # the pose is 6 s behind a completed frame
    dropped = sync.pop_dropped()
    assert [(d.key, d.stamp_ns) for d in dropped] == [("pose", 1 * S)]
    assert "color/depth" in dropped[0].reason
    assert sync.pending("pose") == [] and sync.pending("color") == [4 * S]
    assert sync.pop_dropped() == []
    # A late part of the dropped stamp can no longer complete it.
    sync.add("color", 1 * S, "late")
    assert sync.add("depth", 1 * S, "late") is None


def test_the_number_of_waiting_parts_is_capped():
    sync = StampSync(("color", "depth"), max_age_ns=10**15, max_pending=3)
    for k in range(5):
        sync.add("color", k * S, k)
    assert sync.pending("color") == [2 * S, 3 * S, 4 * S]
    assert [d.stamp_ns for d in sync.pop_dropped()] == [0, 1 * S]


def test_bad_arguments_are_rejected():
    with pytest.raises(InputError, match="^keys: "):
        StampSync(("a", "a"))
    with pytest.raises(InputError, match="^key: "):
        StampSync(("a", "b")).add("c", 0, None)
    with pytest.raises(InputError, match="^max_age_ns: "):
        StampSync(("a",), max_age_ns=-1)


def test_parts_of_a_later_frame_overtaking_an_earlier_one_lose_nothing_whatever_the_stamp_gap():
    """Saved frames replayed faster than captured, hours apart: a later frame's parts arrive
    before the last part of an earlier one, and each frame still completes."""
    hour = 3600 * S
    sync = StampSync(("color", "depth", "pose"), max_age_ns=5 * S)
    assert sync.add("color", 0, "c0") is None
    assert sync.add("pose", 0, "p0") is None
    assert sync.add("color", 3 * hour, "c1") is None
    assert sync.add("pose", 3 * hour, "p1") is None
    assert sync.add("depth", 0, "d0") == {"color": "c0", "depth": "d0", "pose": "p0"}
    assert sync.add("depth", 3 * hour, "d1") == {"color": "c1", "depth": "d1", "pose": "p1"}
    assert sync.pop_dropped() == []


def test_a_part_stamped_far_in_the_future_does_not_push_out_the_frames_in_flight():
    sync = StampSync(("color", "depth"), max_age_ns=5 * S)
    sync.add("color", 10 * S, "c")
    sync.add("depth", 10**9 * S, "from the future")
    assert sync.add("depth", 10 * S, "d") == {"color": "c", "depth": "d"}
    assert sync.pop_dropped() == []


def test_an_old_frame_replayed_after_newer_ones_completed_still_pairs():
    """A restarted node's peers are brought up to date by replaying saved frames, oldest first."""
    hour = 3600 * S
    sync = StampSync(("color", "depth", "pose"), max_age_ns=5 * S)
    for key in ("color", "depth", "pose"):
        sync.add(key, 5 * hour, key)
    for key in ("color", "depth"):
        assert sync.add(key, 1 * hour, key) is None
    assert sync.add("pose", 1 * hour, "p") == {"color": "color", "depth": "depth", "pose": "p"}
    assert sync.pop_dropped() == []


def test_frames_without_camera_info_are_held_in_order_and_the_oldest_go_beyond_capacity():
    held = HeldFrames(capacity=2)
    first = held.hold(1, "a", "area3d/camera/camera_info")
    assert first is not None and "area3d/camera/camera_info" in first  # said once ...
    assert held.hold(2, "b", "area3d/camera/camera_info") is None  # ... not per frame
    assert held.hold(3, "c", "area3d/camera/camera_info") is None
    assert len(held) == 2
    assert held.release() == [(2, "b"), (3, "c")]  # the oldest went beyond capacity
    assert held.dropped == 1  # and is counted (the nodes' status)
    assert len(held) == 0 and held.release() == []
    assert held.hold(4, "d", "info") is not None  # a new wait is said again


def test_a_frame_takes_its_own_stamps_camera_info_else_the_latest():
    cache = CameraInfoCache(size=2)
    assert cache.get(1) is None
    for stamp in (1, 2, 3):
        cache.add(stamp, f"K{stamp}")
    assert cache.get(2) == "K2" and cache.get(3) == "K3"
    assert cache.get(1) == "K3"  # evicted: the latest stands in
    assert cache.get(99) == "K3"


def test_frames_that_never_arrive_are_counted_from_the_gaps_of_a_streaming_camera():
    """30 Hz with whole frames lost on the way (neither part arrives): the pairing rate says so,
    estimated from the gaps between the colour stamps; a pause of the camera is not a loss, nor
    the irregular gaps of a triggered camera (slower than 5 Hz)."""
    ms = 1_000_000
    period = 33 * ms
    sync = StampSync(("color", "depth"), slop_ns=5 * ms, count_gaps=True)
    lost = {i for i in range(20, 200) if i % 3 == 0}  # a third of the frames, after 20 good ones
    for i in range(200):
        if i in lost:
            continue
        jitter = (i % 5) * ms // 2
        sync.add_part("color", i * period + jitter, i)
        sync.add_part("depth", i * period + jitter + ms, i)
    assert sync.frames_missed == len(lost) - (1 if 199 in lost else 0)
    assert sync.frames_paired == 200 - len(lost)
    assert 0.6 < sync.pairing_rate() < 0.72
    # a stream where fewer than one gap in ten is a single period (frames lost and a camera
    # often late) still counts each gap as the frames it lost
    sparse = StampSync(("color", "depth"), count_gaps=True)
    kept = [i for i in range(600) if i < 20 or i % 10 in (0, 3) or i % 60 == 1]
    for i in kept:
        sparse.add_part("color", i * period, i)
        sparse.add_part("depth", i * period, i)
    assert sparse.frames_missed == kept[-1] + 1 - len(kept)
    # and one that never sends two in a row: gaps of two and three periods only
    alternate = StampSync(("color", "depth"), count_gaps=True)
    kept = [i for i in range(300) if i % 5 in (0, 2)]
    for i in kept:
        jitter = (i % 7) * ms // 2
        alternate.add_part("color", i * period + jitter, i)
        alternate.add_part("depth", i * period + jitter, i)
    # the first MIN_GAPS gaps only teach the period
    first_counted = kept[MIN_GAPS]
    assert alternate.frames_missed == sum(
        1 for i in range(first_counted, kept[-1]) if i not in kept
    )
    # a camera that pauses 3 s and resumes loses nothing
    paused = StampSync(("color", "depth"), count_gaps=True)
    for i in list(range(30)) + list(range(120, 150)):
        paused.add_part("color", i * period, i)
        paused.add_part("depth", i * period, i)
    assert paused.frames_missed == 0 and paused.pairing_rate() == 1.0
    # a triggered camera, one frame per view every few seconds: not a stream
    triggered = StampSync(("color", "depth"), count_gaps=True)
    stamp = 0
    for i in range(30):
        stamp += (2000 + 700 * (i % 4)) * ms
        triggered.add_part("color", stamp, i)
        triggered.add_part("depth", stamp, i)
    assert triggered.frames_missed == 0


def test_a_stream_stamped_late_by_up_to_most_of_a_period_loses_nothing_by_its_gaps():
    """A 5 Hz driver stamping when it publishes, on a loaded machine: each stamp up to 160 ms
    late, every frame delivered. Its shortest gaps (40-60 ms) are no period: read as one, every
    frame counted as several lost, and the pairing rate read 0.3-0.6 (a warning that never
    cleared)."""
    rng = random.Random(3)
    period = 200_000_000
    sync = StampSync(("color", "depth"), count_gaps=True)
    for i in range(300):
        stamp = i * period + int(rng.uniform(0, 160_000_000))
        sync.add_part("color", stamp, i)
        sync.add_part("depth", stamp, i)
    assert sync.frames_missed == 0 and sync.pairing_rate() == 1.0


def test_a_frame_published_late_then_one_on_time_is_no_frame_lost():
    """A 5 Hz driver stamping when it publishes, 10 ms of jitter, one frame in twenty up to
    250 ms late and the next on time: its gaps of 50-150 ms were taken for the period, and
    every on-time gap of 200 ms counted as a frame lost (a burst of 75 missed over 98 frames,
    nothing lost). The median gap is the period: only a gap of more than 1.5 periods counts,
    and one of less than half a period after it takes that count back."""
    rng = random.Random(5)
    period = 200_000_000
    sync = StampSync(("color", "depth"), count_gaps=True)
    late = 0
    for i in range(400):
        delay = int(rng.gauss(0, 5_000_000))
        if i % 20 == 7:
            delay += int(rng.uniform(100_000_000, 250_000_000))
            late += delay > 90_000_000  # the frames whose gap can read as 2 periods
        sync.add_part("color", i * period + delay, i)
        sync.add_part("depth", i * period + delay, i)
    assert late >= 10  # frames late by more than half a period: their gaps read as 2 periods
    # the short gap after each takes its frame back: nothing lost, nothing counted
    assert sync.frames_missed == 0 and sync.pairing_rate() == 1.0
    # a frame late by more than half a period with the next one lost: one missed, as it is
    lossy = StampSync(("color", "depth"), count_gaps=True)
    for i in [*range(20), 20, 22, 23, 24]:
        delay = 130_000_000 if i == 20 else 0
        lossy.add_part("color", i * period + delay, i)
        lossy.add_part("depth", i * period + delay, i)
    assert lossy.frames_missed == 1 and lossy.frames_paired == 24


def test_a_driver_rate_counts_the_frames_of_a_stream_that_loses_most_of_them():
    """30 Hz, one slot in three sent (a driver late for two): gaps of three periods only, which
    the learnt period reads as a 10 Hz stream losing nothing; given the driver's rate every
    missing slot counts, from the first gap on; a pause over 1 s still is a pause."""
    period = 33_333_333
    kept = [i for i in range(300) if i % 3 == 0] + list(range(400, 430))
    learnt = StampSync(("color", "depth"), count_gaps=True)
    nominal = StampSync(("color", "depth"), count_gaps=True, period_ns=period)
    for sync in (learnt, nominal):
        for i in kept:
            stamp = i * period + (i % 4) * 1_000_000  # a millisecond or so of jitter
            sync.add_part("color", stamp, i)
            sync.add_part("depth", stamp, i)
    assert learnt.frames_missed == 0
    # two per gap up to frame 297; the gap from 297 to 400 (3.4 s) is the camera pausing
    assert nominal.frames_missed == 2 * 99
    assert nominal.pairing_rate() < 0.6 and learnt.pairing_rate() == 1.0
    with pytest.raises(InputError, match="^period_ns: "):
        StampSync(("color",), count_gaps=True, period_ns=-1)
