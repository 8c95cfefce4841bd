"""decode: peaks, sub-pixel positions, grouping corners to centroids through the affinity."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from dope_hope.catalog import get_object
from dope_hope.errors import ConfigError
from dope_hope.geometry import (
    cuboid_keypoints,
    intrinsics_matrix,
    project_points,
    scale_intrinsics,
)
from dope_hope.maps.decode import (
    DecodeSettings,
    Instance2D,
    assign_corners,
    corner_candidates,
    decode_maps,
)
from dope_hope.maps.targets import head_defaults, make_targets

# A 640x480 camera seen through a 400x300 network input ("the 400-px scale").
K400 = scale_intrinsics(intrinsics_matrix(615.0, 615.0, 319.5, 239.5), 400 / 640, 300 / 480)
HW = (300, 400)


def _match(instances: list[Instance2D], kp: np.ndarray) -> list[int]:
    """Index of the ground-truth instance nearest to each decoded centroid."""
    return [int(np.argmin(np.linalg.norm(kp[:, 8] - inst.keypoints[8], axis=1))) for inst in instances]


def _scene(seed: int = 0) -> np.ndarray:
    cub = cuboid_keypoints(get_object("Popcorn").size_array)
    ts = [np.array([-0.15, 0.02, 0.7]), np.array([0.06, -0.06, 0.9]), np.array([0.2, 0.09, 0.6])]
    Rs = Rotation.random(3, random_state=seed).as_matrix()
    return np.stack([project_points(cub, K400, R, t) for R, t in zip(Rs, ts)])


@pytest.mark.parametrize("stride", [8, 1])
def test_every_instance_comes_back_with_its_own_keypoints(stride):
    kp = _scene()
    b, a = make_targets(kp, HW, stride)
    inst = decode_maps(b, a, stride)
    assert len(inst) == 3
    assert sorted(_match(inst, kp)) == [0, 1, 2]
    for i, j in zip(inst, _match(inst, kp)):
        assert i.present.all()
        np.testing.assert_allclose(i.keypoints, kp[j], atol=0.05)
        np.testing.assert_allclose(i.scores, 1.0, atol=1e-3)  # fitted Gaussian height
        assert i.score == pytest.approx(i.scores.sum() / 9)


def test_missing_keypoints_stay_nan_with_zero_score():
    kp = _scene()
    kp[:, [0, 3, 5]] = np.nan
    b, a = make_targets(kp, HW, 8)
    inst = decode_maps(b, a, 8)
    assert len(inst) == 3
    for i in inst:
        assert i.present.tolist() == [False, True, True, False, True, False, True, True, True]
        assert np.all(i.scores[[0, 3, 5]] == 0)
        assert i.score == pytest.approx(6 / 9, abs=1e-3)


def test_torch_tensors_and_a_batch_of_one_decode_like_numpy():
    kp = _scene(1)
    b, a = make_targets(kp, HW, 8)
    ref = decode_maps(b, a, 8)
    got = decode_maps(torch.from_numpy(b)[None], torch.from_numpy(a)[None], 8)
    assert len(got) == len(ref) == 3
    for r, g in zip(ref, got):
        np.testing.assert_allclose(g.keypoints, r.keypoints)
    with pytest.raises(ValueError, match="one image at a time"):
        decode_maps(torch.from_numpy(np.stack([b, b])), torch.from_numpy(np.stack([a, a])), 8)
    with pytest.raises(ValueError):
        decode_maps(b[:8], a, 8)


@pytest.mark.parametrize("seed", range(5))
def test_noise_below_the_threshold_gives_no_detection(seed):
    """What a network outputs on background: weak, smooth or speckled, under the threshold."""
    rng = np.random.default_rng(seed)
    smooth = gaussian_filter(rng.normal(size=(9, 37, 50)), (0, 1.5, 1.5))
    belief = 0.06 * np.abs(smooth) / np.abs(smooth).max() + rng.uniform(0, 0.03, (9, 37, 50))
    affinity = rng.normal(0, 1, (16, 37, 50))
    assert decode_maps(belief.astype(np.float32), affinity.astype(np.float32), 8) == []
    assert decode_maps(np.zeros((9, 37, 50)), np.zeros((16, 37, 50)), 8) == []


def test_threshold_drops_weak_keypoints():
    kp = _scene()
    b, a = make_targets(kp, HW, 8)
    b[2] *= 0.3  # corner 2 only weakly believed
    assert all(i.present[2] for i in decode_maps(b, a, 8, DecodeSettings(threshold=0.1)))
    assert not any(i.present[2] for i in decode_maps(b, a, 8, DecodeSettings(threshold=0.5)))


def test_corners_whose_field_points_away_from_every_centroid_are_not_assigned():
    kp = _scene()[:1]
    b, a = make_targets(kp, HW, 8)
    assert decode_maps(b, a, 8)[0].present.all()
    inst = decode_maps(b, -a, 8)  # every vector reversed
    assert len(inst) == 1
    assert inst[0].present.tolist() == [False] * 8 + [True]
    assert decode_maps(b, -a, 8, DecodeSettings(min_keypoints=2)) == []


def test_a_corner_nearer_to_another_centroid_follows_its_field():
    """Nearest centroid alone would give corner A to B; the angle test keeps it with A."""
    centroids = np.array([[10.0, 10.0], [22.0, 10.0]])  # A, B (map px)
    corners = np.array([[17.0, 10.0], [22.0, 16.0]])     # A's (nearer to B!), B's
    vectors = np.array([[-1.0, 0.0], [0.0, -1.0]])       # A's points left, B's up
    owner = assign_corners(corners.astype(int), corners, vectors, centroids)
    assert owner.tolist() == [0, 1]
    # Without a usable field (below min_affinity) nothing is assigned.
    assert assign_corners(corners.astype(int), corners, 0.01 * vectors, centroids,
                          min_affinity=0.1).tolist() == [-1, -1]


def test_two_corners_of_one_type_never_go_to_the_same_instance():
    centroids = np.array([[10.0, 10.0]])
    corners = np.array([[14.0, 10.0], [15.0, 11.0]])
    vectors = centroids - corners
    owner = assign_corners(corners.astype(int), corners, vectors, centroids)
    assert sorted(owner.tolist()) == [-1, 0] and owner[0] == 0  # the nearer one wins


@pytest.mark.parametrize("stride", [8, 1])
def test_two_touching_instances_are_not_merged(stride):
    """Two soup cans side by side (boxes sharing a face) at 1 m: centroids 25 px apart."""
    size = get_object("AlphabetSoup").size_array
    cub = cuboid_keypoints(size)
    R = Rotation.from_euler("xyz", [20, 10, 5], degrees=True).as_matrix()
    ts = [np.array([0, 0, 1.0]) + R @ np.array([s * size[0] / 2, 0, 0]) for s in (-1, 1)]
    kp = np.stack([project_points(cub, K400, R, t) for t in ts])
    assert np.linalg.norm(kp[0, 8] - kp[1, 8]) < 4 * 8  # closer than 4 cells at stride 8
    b, a = make_targets(kp, HW, stride)
    inst = decode_maps(b, a, stride)
    assert len(inst) == 2 and sorted(_match(inst, kp)) == [0, 1]
    for i, j in zip(inst, _match(inst, kp)):
        assert i.present.all()
        np.testing.assert_allclose(i.keypoints, kp[j], atol=0.05)
    if stride == 8:
        # DOPE's own smoothing (sigma 3 map px) merges them: why the default is smaller.
        assert len(decode_maps(b, a, stride, DecodeSettings(smooth_sigma=3.0))) < 2


def test_refinement_on_the_smoothed_map_stays_within_a_pixel():
    kp = _scene(2)
    _, radius = head_defaults(8)
    b, a = make_targets(kp, HW, 8, sigma=2.0, radius=radius)
    inst = decode_maps(b, a, 8, DecodeSettings(refine_on="smoothed"))
    assert len(inst) == 3
    for i, j in zip(inst, _match(inst, kp)):
        assert np.abs(i.keypoints - kp[j]).max() < 1.0
    with pytest.raises(ConfigError, match="refine_on"):
        decode_maps(b, a, 8, DecodeSettings(refine_on="centroid"))


def test_a_strong_corner_peak_beats_a_weak_one_nearer_to_the_centroid():
    """Trained nets leave weak secondary peaks; grouping by distance alone took the weak one
    next to the centroid instead of the true corner (a third of a trained model's corners)."""
    centroids = np.array([[10.0, 10.0]])
    corners = np.array([[18.0, 10.0], [12.0, 10.0]])  # the true corner far, a weak peak near
    vectors = centroids - corners                      # both point at the centroid
    owner = assign_corners(corners.astype(int), corners, vectors, centroids,
                           corner_scores=np.array([0.9, 0.2]))
    assert owner.tolist() == [0, -1]
    # equal scores: DOPE's nearest-centroid rule
    owner = assign_corners(corners.astype(int), corners, vectors, centroids,
                           corner_scores=np.array([0.5, 0.5]))
    assert owner.tolist() == [-1, 0]


def test_a_spurious_centroid_takes_the_true_corner_in_the_one_to_one_grouping_not_from_the_candidates():
    """The true corner's field also points at a spurious centroid lying on the way to the
    true one; a weak stray peak is feasible for the true centroid alone. One-to-one must
    use both peaks and crosses them; as candidates, both centroids keep the true corner."""
    centroids = np.array([[10.0, 10.0], [16.0, 10.0]])   # true, spurious (on the segment)
    corners = np.array([[20.0, 10.0], [10.0, 15.0]])      # true corner, weak stray peak
    vectors = np.array([[-1.0, 0.0], [0.0, -1.0]])        # both point at the true centroid
    scores = np.array([0.9, 0.5])
    owner = assign_corners(corners.astype(int), corners, vectors, centroids, corner_scores=scores)
    assert owner.tolist() == [1, 0]  # the true centroid got the stray peak
    # The same peaks as maps: corner type 0 at the two corners, centroid peaks at both.
    belief = np.zeros((9, 24, 32), np.float32)
    affinity = np.zeros((16, 24, 32), np.float32)
    for (x, y), s in zip(corners.astype(int), scores):
        belief[0, y, x] = s
    for x, y in centroids.astype(int):
        belief[8, y, x] = 1.0 if x == 10 else 0.8
    for (x, y), v in zip(corners.astype(int), vectors):
        affinity[0:2, y, x] = v
    cands = corner_candidates(belief, affinity, 1, DecodeSettings(smooth_sigma=0))
    assert len(cands) == 2 and cands[0].score == pytest.approx(1.0)   # strongest centroid first
    true, spurious = cands
    assert true.keypoint_ids.tolist() == [8, 0, 0] and spurious.keypoint_ids.tolist() == [8, 0]
    # The one-to-one choice first (the stray peak for the true centroid), then the rest.
    np.testing.assert_allclose(true.xy, [[10, 10], [10, 15], [20, 10]], atol=1e-6)
    np.testing.assert_allclose(spurious.xy[1], [20, 10], atol=1e-6)
    np.testing.assert_allclose(true.scores[1:], scores[::-1], atol=1e-6)
    one = corner_candidates(belief, affinity, 1, DecodeSettings(smooth_sigma=0, max_per_type=1))
    assert one[0].keypoint_ids.tolist() == [8, 0]
    np.testing.assert_allclose(one[0].xy[1], [10, 15], atol=1e-6)
    with pytest.raises(ConfigError, match="max_per_type"):
        corner_candidates(belief, affinity, 1, DecodeSettings(max_per_type=0))


@pytest.mark.parametrize("stride", [8, 1])
def test_every_instance_keeps_its_own_corners_among_its_candidates(stride):
    kp = _scene(1)
    b, a = make_targets(kp, HW, stride)
    cands = corner_candidates(b, a, stride)
    assert len(cands) == 3
    for c in cands:
        j = int(np.argmin(np.linalg.norm(kp[:, 8] - c.xy[0], axis=1)))
        for k in range(9):
            own = c.xy[c.keypoint_ids == k]
            assert np.min(np.linalg.norm(own - kp[j, k], axis=1)) < 0.05


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_another_objects_corner_that_passes_the_angle_test_is_no_candidate():
    """Object A (centroid at x=10) has corners 0-2 five cells away; object B (centroid at
    x=30) has a type-3 corner on the far side (x=34) and a type-4 corner below right of it. Both
    B corners pass A's angle test (their fields point at B, A lies within 29 deg of that), yet
    neither is A's candidate: the type-3 corner lies 24 cells from A (more than twice A's
    size, 5 cells), the type-4 field points at B 0.39 (unit-vector distance) better than at A.
    Without the bounds, both are."""
    A, B = np.array([10.0, 10.0]), np.array([30.0, 10.0])
    belief = np.zeros((9, 24, 48), np.float32)
    affinity = np.zeros((16, 24, 48), np.float32)
    corners = {0: (10, 5), 1: (15, 10), 2: (10, 15), 3: (34, 10), 4: (42, 20)}
    for k, (x, y) in corners.items():
        belief[k, y, x] = 1.0
        affinity[2 * k: 2 * k + 2, y, x] = _unit((A if k < 3 else B) - [x, y])
    for x, y in (A, B):
        belief[8, int(y), int(x)] = 1.0
    assert np.linalg.norm(affinity[8:10, 20, 42] - _unit(A - corners[4])) < 0.5   # feasible for A

    def candidates_of_a(**kw) -> list[int]:
        cands = corner_candidates(belief, affinity, 1, DecodeSettings(smooth_sigma=0, **kw))
        return sorted(next(c for c in cands if np.allclose(c.xy[0], A)).keypoint_ids.tolist())

    assert candidates_of_a() == [0, 1, 2, 8]
    assert candidates_of_a(angle_margin=np.inf, size_factor=np.inf) == [0, 1, 2, 3, 4, 8]
    assert candidates_of_a(angle_margin=np.inf) == [0, 1, 2, 8]          # the size bound alone
    assert candidates_of_a(size_factor=np.inf) == [0, 1, 2, 3, 8]        # the angle margin alone
    with pytest.raises(ConfigError, match="angle_margin"):
        corner_candidates(belief, affinity, 1, DecodeSettings(angle_margin=-1.0))


# ----------------------------------------------------------------------------- noise floor
def _noisy(b: np.ndarray, a: np.ndarray, sb: float, sa: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    return ((b + rng.normal(0.0, sb, b.shape)).astype(np.float32),
            (a + rng.normal(0.0, sa, a.shape)).astype(np.float32))


def test_heavy_noise_leaves_the_true_peaks_not_every_noise_blob():
    """Belief noise of std 0.1 (the peak threshold) and affinity noise 0.3 at stride 8: every
    noise blob passes the threshold alone (~150 peaks per channel on 50x38 maps); with the
    noise floor each centroid's candidates are its own box's, as on clean maps."""
    from dope_hope.maps.peaks import find_peaks

    kp = _scene(2)
    b, a = make_targets(kp, HW, 8)
    nb, na = _noisy(b, a, 0.1, 0.3)
    assert np.bincount(find_peaks(nb, noise_sigmas=0.0).channel, minlength=9).min() > 40  # no floor: noise everywhere
    cands = corner_candidates(nb, na, 8)
    assert len(cands) == 3
    for c in cands:
        j = int(np.argmin(np.linalg.norm(kp[:, 8] - c.xy[0], axis=1)))
        near = np.linalg.norm(c.xy - kp[j, c.keypoint_ids], axis=1) < 8.0
        assert near.mean() > 0.8
    assert len(corner_candidates(nb, na, 8, DecodeSettings(noise_sigmas=0.0))) > 30       # the floor is what drops them
    assert decode_maps(*_noisy(np.zeros_like(b), np.zeros_like(a), 0.1, 0.3, seed=1), 8) == []


def test_noise_floor_leaves_clean_and_lightly_noisy_maps_as_they_were():
    kp = _scene(3)
    b, a = make_targets(kp, HW, 8)
    for maps in ((b, a), _noisy(b, a, 0.01, 0.05)):
        with_floor = corner_candidates(*maps, 8)
        without = corner_candidates(*maps, 8, DecodeSettings(noise_sigmas=0.0))
        assert len(with_floor) == len(without) == 3
        for c, d in zip(with_floor, without):
            assert c.keypoint_ids.tolist() == d.keypoint_ids.tolist()
            np.testing.assert_array_equal(c.xy, d.xy)
    with pytest.raises(ConfigError, match="noise_sigmas"):
        corner_candidates(b, a, 8, DecodeSettings(noise_sigmas=-1.0))


@pytest.mark.parametrize("options", [{}, {"noise_sigmas": 0.0, "threshold": 0.2},
                                     {"smooth_sigma": 0.0, "refine_on": "smoothed", "angle_threshold": 0.6}])
def test_peaks_found_once_decode_as_the_decoders_find_them(options):
    """decoder_peaks(maps, settings) are the peaks both decoders find themselves: handed in,
    they give the same instances and candidates; keypoint_score_bound of the peaks is the best type's peaks' mean."""
    from dope_hope.maps.decode import decoder_peaks, keypoint_score_bound

    b, a = make_targets(_scene(), HW, 8)
    b, a = _noisy(b, a, 0.08, 0.2, seed=3)
    settings = DecodeSettings(**options)
    peaks = decoder_peaks(b, settings)
    for decode in (decode_maps, corner_candidates):
        mine, theirs = decode(b, a, 8, settings, peaks=peaks), decode(b, a, 8, settings)
        assert len(mine) == len(theirs) > 0
        for x, y in zip(mine, theirs):
            for field in x.__dataclass_fields__:
                np.testing.assert_array_equal(getattr(x, field), getattr(y, field))
    best = [np.clip(peaks.score[peaks.channel == k], 0, 1).max(initial=0.0) for k in range(9)]

    def pose_score_bound(peaks, min_points=None):
        return keypoint_score_bound(peaks.channel, peaks.score, min_points)

    assert pose_score_bound(peaks) == pytest.approx(sum(best) / 9)
    clipped = [np.clip(inst.scores, 0, 1).sum() / 9 for inst in decode_maps(b, a, 8, settings)]
    assert max(clipped) <= pose_score_bound(peaks) + 1e-12
    # the in-view score's bound (divided by at least 5 keypoints): the 5 best types' mean
    assert pose_score_bound(peaks, 5) == pytest.approx(sum(sorted(best)[-5:]) / 5)
    assert pose_score_bound(peaks, 9) == pytest.approx(pose_score_bound(peaks))
    # heights above 1 count as 1; NaN, negative and missing types as 0
    assert keypoint_score_bound([0, 0, 3, 5, 8], [0.4, 1.7, np.nan, -0.2, 0.6], 2) == pytest.approx(0.8)
    assert keypoint_score_bound([], [], 5) == 0.0 and keypoint_score_bound([2], [0.9]) == pytest.approx(0.1)


def test_find_peaks_defaults_are_the_decoders():
    """The peak options have one owner, the decoder's settings: a bare find_peaks (validation,
    benches) finds the peaks inference finds, noise floor included."""
    import inspect

    from dope_hope.maps.decode import PEAK_OPTIONS
    from dope_hope.maps.peaks import find_peaks

    defaults = {k: p.default for k, p in inspect.signature(find_peaks).parameters.items() if k in PEAK_OPTIONS}
    assert defaults == {k: getattr(DecodeSettings(), k) for k in PEAK_OPTIONS}
