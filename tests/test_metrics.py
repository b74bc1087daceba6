"""Metric functions on hand-worked cases (expected values derived in each docstring)."""

from __future__ import annotations

import numpy as np
import pytest

from aynamics import metrics
from aynamics import scene as scenelib


def _seg(*frames):
    return np.array(frames, dtype=np.int16)


def test_iou_hand_case():
    """Predicted mask 4 px, observed 4 px, 2 shared: IoU = 2 / (4 + 4 - 2) = 1/3."""
    obs = _seg([[0, 0, 0, 0, -1, -1]])
    pred = _seg([[-1, -1, 0, 0, 0, 0]])
    first, full = metrics.segmentation_iou(pred, obs)
    assert first == pytest.approx(1 / 3) and full == pytest.approx(1 / 3)


def test_iou_matching_by_overlap_and_by_name():
    """Swapped ids match by overlap (IoU 1); forced by names to the wrong partner, IoU is 0."""
    obs = _seg([[0, 0, 1, 1]])
    pred = _seg([[1, 1, 0, 0]])
    assert metrics.segmentation_iou(pred, obs) == (1.0, 1.0)
    first, _ = metrics.segmentation_iou(pred, obs, pred_names=("a", "b"), obs_names=("a", "b"))
    assert first == 0.0
    first, _ = metrics.segmentation_iou(pred, obs, pred_names=("b", "a"), obs_names=("a", "b"))
    assert first == 1.0


def test_iou_per_frame_average_and_missing_objects():
    """Frame 0: one object, exact (1). Frame 1: observed object 1 is missing from the prediction:
    (1 + 0) / 2 = 0.5. Full = (1 + 0.5) / 2 = 0.75. Frames where nothing is visible on either side score 1."""
    obs = _seg([[0, 0, -1, -1]], [[0, 0, 1, 1]], [[-1, -1, -1, -1]])
    pred = _seg([[0, 0, -1, -1]], [[0, 0, -1, -1]], [[-1, -1, -1, -1]])
    counts = metrics.overlap_counts(pred, obs, 1, 2)
    per_frame = metrics.iou_from_counts(counts)
    np.testing.assert_allclose(per_frame, [1.0, 0.5, 1.0])
    assert counts[:, 0, 0].tolist() == [2, 0, 4]  # background-background pixels per frame
    # the prediction still shows the object in frame 1 after it left the observed view: 0 / 1 there, not an
    # empty frame's 1 (a matched pair counts once only when both sides show it)
    gone = metrics.iou_from_counts(metrics.overlap_counts(_seg([[0, 0]], [[0, 0]]), _seg([[0, 0]], [[-1, -1]]), 1, 1))
    np.testing.assert_allclose(gone, [1.0, 0.0])


def test_iou_falls_with_shift():
    obs = np.full((1, 20, 40), -1, np.int16)
    obs[0, 5:15, 10:20] = 0
    values = []
    for shift in range(0, 12, 2):
        pred = np.full_like(obs, -1)
        pred[0, 5:15, 10 + shift : 20 + shift] = 0
        values.append(metrics.segmentation_iou(pred, obs)[0])
    assert values[0] == 1.0 and values[-1] == 0.0
    assert all(a > b for a, b in zip(values, values[1:-1], strict=False))


def test_epe_hand_case():
    """4 observed object pixels, one off by (3, 4), the rest exact: EPE = 5 / 4 = 1.25 px. Errors off the observed
    objects do not count: a still predicted object on still floor does not dilute it (over both sides' object
    pixels it would be 5 / 5), a moving one does not inflate it (the IoU scores extra objects)."""
    obs = np.zeros((1, 2, 3, 2))
    pred = np.zeros((1, 2, 3, 2))
    pred[0, 0, 0] = (3.0, 4.0)
    pred[0, 1, 2] = (100.0, 0.0)  # on no object of either side
    obs_seg = _seg([[0, 0, -1], [0, 0, -1]])
    assert metrics.flow_epe(pred, obs, obs_seg, obs_seg) == (1.25, 1.25)
    extra = _seg([[0, 0, 1], [0, 0, -1]])  # a predicted object over (0, 2), where the video shows none
    assert metrics.flow_epe(pred, obs, extra, obs_seg) == (1.25, 1.25)
    pred[0, 0, 2] = (0.0, 2.0)  # ... moving
    assert metrics.flow_epe(pred, obs, extra, obs_seg) == (1.25, 1.25)


def test_epe_over_the_observed_objects_else_the_predicted():
    """Frame 0 shows no object on either side (nan, skipped; 0 as the first-frame figure, as in the scorer),
    frame 1 an observed object pixel with an error of 2 beside a predicted-only pixel: 2 / 1; frame 2 only a
    predicted object moving by 3 over 2 pixels, where nothing is observed: 3."""
    obs = np.zeros((3, 1, 2, 2))
    pred = np.zeros((3, 1, 2, 2))
    pred[1, 0, 0] = (0.0, 2.0)
    pred[1, 0, 1] = (50.0, 0.0)
    pred[2, 0, :] = (3.0, 0.0)
    obs_seg = np.array([[[-1, -1]], [[0, -1]], [[-1, -1]]])
    pred_seg = np.array([[[-1, -1]], [[0, 1]], [[0, 0]]])
    per = metrics.flow_epe_frames(pred, obs, pred_seg, obs_seg)
    assert np.isnan(per[0]) and per[1:].tolist() == [2.0, 3.0]
    assert metrics.epe_mask(pred_seg, obs_seg).tolist() == [[[False, False]], [[True, False]], [[True, True]]]
    first, full = metrics.flow_epe(pred, obs, pred_seg, obs_seg)
    assert first == 0.0 and full == 2.5
    with pytest.raises(ValueError, match="flow shapes differ"):
        metrics.flow_epe(pred, obs[:1], pred_seg, obs_seg)


def test_malformed_segmentations_are_refused_not_scored():
    """A (H, W) mask pair was scored as H one-row frames (this pair, IoU 1/3 as one frame: (0.0, 0.5)); float ids
    were truncated (0.7 scored as object 0: 1/3), ids below -1 were background (IoU 0), and one id of 10**9 asked
    NumPy for a 16 GB histogram. Each is now a ValueError naming the argument and the value."""
    obs = _seg([[0, 0, 0, 0, -1, -1]])
    pred = _seg([[-1, -1, 0, 0, 0, 0]])
    assert metrics.segmentation_iou(pred, obs) == (1 / 3, 1 / 3)
    with pytest.raises(ValueError, match=r"pred_seg: shape \(1, 6\): must be \(frames, height, width\)"):
        metrics.segmentation_iou(pred[0], obs[0])
    with pytest.raises(ValueError, match=r"obs_seg: shape \(0, 1, 6\): .* at least one frame"):
        metrics.segmentation_iou(pred, obs[:0])
    with pytest.raises(ValueError, match=r"pred_seg: value 0.7 at frame 0, row 0, column 2: ids must be whole"):
        metrics.segmentation_iou(np.where(pred >= 0, 0.7, -1.0), obs)
    with pytest.raises(ValueError, match=r"pred_seg: value nan at frame 0, row 0, column 2"):
        metrics.segmentation_iou(np.where(pred >= 0, np.nan, -1.0), obs)
    assert metrics.segmentation_iou(pred.astype(float), obs) == (1 / 3, 1 / 3)  # whole-valued floats are ids
    with pytest.raises(ValueError, match=r"obs_seg: id -5 at frame 0, row 0, column 0: must be -1"):
        metrics.segmentation_iou(pred, np.where(obs >= 0, -5, -1))
    with pytest.raises(ValueError, match=r"pred_seg: dtype bool"):
        metrics.segmentation_iou(pred >= 0, obs >= 0)
    with pytest.raises(ValueError, match=r"object ids up to 1000000000 \(predicted\) and 0 \(observed\)"):
        metrics.segmentation_iou(np.where(pred >= 0, 10**9, -1), obs)


def test_epe_of_malformed_or_non_finite_flow_is_refused():
    """The hand case above (EPE 1.25) with a NaN predicted vector on the off pixel scored (0.0, 0.0), a perfect EPE
    (the frame dropped as empty); a (1, H, W) predicted segmentation and an (H, W) occlusion mask were broadcast
    over the frames; flows with 3 components were scored on the first two."""
    obs = np.zeros((2, 2, 3, 2))
    pred = np.zeros((2, 2, 3, 2))
    pred[0, 0, 0] = (3.0, 4.0)
    seg = np.array([[[0, 0, -1], [0, 0, -1]]] * 2)
    assert metrics.flow_epe(pred, obs, seg, seg) == (1.25, 0.625)
    pred[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"pred_flow: 1 NaN or infinite vectors .* at frame 0, row 0, column 0\)"):
        metrics.flow_epe(pred, obs, seg, seg)
    pred[0, 0, 0] = (3.0, 4.0)
    pred[0, 1, 2] = np.inf  # on no object: never read
    assert metrics.flow_epe(pred, obs, seg, seg) == (1.25, 0.625)
    obs[1, 0, 1] = (np.inf, 0.0)
    with pytest.raises(ValueError, match=r"obs_flow: 1 NaN or infinite vectors .* \(the first \[inf, 0.0\] at frame 1"):
        metrics.flow_epe(pred, obs, seg, seg)
    occ = np.zeros((2, 2, 3), bool)
    occ[1, 0, 1] = True  # occluded there: not read
    assert metrics.flow_epe(pred, obs, seg, seg, occ) == (1.25, 0.625)
    obs[1, 0, 1] = 0.0
    with pytest.raises(ValueError, match=r"segmentation shapes differ: predicted \(1, 2, 3\), observed \(2, 2, 3\)"):
        metrics.flow_epe(pred, obs, seg[:1], seg)
    with pytest.raises(ValueError, match=r"obs_occluded: shape \(2, 3\), expected the segmentations' \(2, 2, 3\)"):
        metrics.flow_epe(pred, obs, seg, seg, occ[0])
    with pytest.raises(ValueError, match=r"obs_occluded: dtype float64 with values other than 0 and 1"):
        metrics.flow_epe(pred, obs, seg, seg, np.full((2, 2, 3), 0.5))
    with pytest.raises(ValueError, match=r"flow shapes differ: predicted \(2, 2, 3, 3\)"):
        metrics.flow_epe(np.zeros((2, 2, 3, 3)), np.zeros((2, 2, 3, 3)), seg, seg)


def test_epe_mask_leaves_out_occluded_flow():
    pred = _seg([[0, -1, -1, 0]])
    obs = _seg([[-1, 0, -1, 0]])
    occ = np.array([[[False, False, False, True]]])
    assert metrics.epe_mask(pred, obs, occ).tolist() == [[[False, True, False, False]]]
    # every observed pixel occluded: as a frame without observed objects, the predicted pixels (not occluded)
    assert metrics.epe_mask(pred, _seg([[-1, -1, -1, 0]]), occ).tolist() == [[[True, False, False, False]]]


def _scene(objects: str) -> scenelib.Scene:
    return scenelib.parse(objects + "- type: camera\n  position: [0, -2, 3.5]\n")


def test_state_mae_and_matching_by_position():
    """Names differ, so pairs come from nearest initial positions. Errors: positions (0.3, 0, 0) and (0, 0, 0),
    velocities (0, 0.6, 0) and (0, 0, 0) -> MAE over 2 objects x 3 components: 0.3 / 6 = 0.05, 0.6 / 6 = 0.1."""
    obs = _scene(
        "- {type: sphere, name: a, radius: 0.2, state: {position: [0, 0, 0.2]}}\n"
        "- {type: box, name: b, size: [0.2, 0.2, 0.2], state: {position: [3, 0, 0.2], linear_velocity: [1, 0, 0]}}\n"
    )
    pred = _scene(
        "- {type: box, name: x, size: [0.2, 0.2, 0.2], state: {position: [3, 0, 0.2], linear_velocity: [1, 0.6, 0]}}\n"
        "- {type: sphere, name: y, radius: 0.2, state: {position: [0.3, 0, 0.2]}}\n"
    )
    pos, vel = metrics.state_mae(pred, obs)
    assert pos == pytest.approx(0.05) and vel == pytest.approx(0.1)
    assert metrics.state_mae_batch(["not: a scene"], [obs]) == [
        (metrics.POSITION_MAE_INVALID, metrics.VELOCITY_MAE_INVALID)
    ]


def test_state_mae_counts_every_object():
    """A 3-object video predicted as one of its objects, exactly: the other two are scored against it (position
    errors (2, 0, 0) and (0, 4, 0), velocity errors (1, 0, 0) twice) -> 6 / 9 m and 2 / 9 m/s, not 0. Extra
    predicted objects are not scored: copies of a well-placed object cannot lower the mean, nor a stray one raise
    it (the count accuracy sees both)."""
    obj = "- {{type: box, size: [0.2, 0.2, 0.2], state: {{position: [{}, {}, 0.1], linear_velocity: [{}, 0, 0]}}}}\n"
    truth = _scene(obj.format(0, 0, 0) + obj.format(2, 0, 1) + obj.format(0, 4, 1))
    one = _scene(obj.format(0, 0, 0))
    assert metrics.state_mae(one, truth) == pytest.approx((6 / 9, 2 / 9))
    extra = _scene(obj.format(0, 0, 0) + obj.format(2, 0, 1) + obj.format(0, 4, 1) + obj.format(3, 0, 1))
    assert metrics.state_mae(extra, truth) == pytest.approx((0.0, 0.0))
    off = _scene(obj.format(0.3, 0, 0) + obj.format(2, 0, 1) + obj.format(0, 4, 1))  # 0.3 m off: 0.3 / 9
    padded = _scene(obj.format(0.3, 0, 0) + obj.format(2, 0, 1) + obj.format(0, 4, 1) + obj.format(2.01, 0, 1) * 3)
    assert metrics.state_mae(off, truth)[0] == pytest.approx(0.3 / 9) == metrics.state_mae(padded, truth)[0]


def test_composition_accuracy():
    obs = _scene("- {type: sphere, radius: 0.2, state: {position: [0, 0, 0.2]}}\n")
    same = _scene("- {type: sphere, radius: 0.5, state: {position: [1, 0, 0.5]}}\n")
    other = _scene("- {type: box, size: [0.2, 0.2, 0.2], state: {position: [1, 0, 0.2]}}\n")
    count, shapes = metrics.composition_accuracy([same, other, "]]"], [obs, obs, obs])
    assert count == [1.0, 1.0, 0.0] and shapes == [1.0, 0.0, 0.0]


def test_match_objects_names_first():
    score = np.array([[0.0, 0.9], [0.8, 0.0]])
    # "a" pairs by name despite zero overlap; "b" and "c" do not overlap, so they stay unmatched
    assert metrics.match_objects(["a", "b"], ["a", "c"], score) == [(0, 0)]
    assert metrics.match_objects(None, None, score) == [(0, 1), (1, 0)]


def test_match_objects_names_a_name_that_is_not_a_str():
    """None among the predicted names failed on a bare TypeError in the default-name regex ("expected string or
    bytes-like object"), and among the observed ones it silently matched nothing. Names as a tuple or a NumPy array
    of str pair as a list does: "a" with "a" by name, then "b" / "c" (overlap 0) left unpaired."""
    score = np.array([[0.0, 0.9], [0.8, 0.0]])
    with pytest.raises(ValueError, match=r"match_objects: pred_names\[1\] = None: object names must be str"):
        metrics.match_objects(["a", None], ["a", "c"], score)
    with pytest.raises(ValueError, match=r"match_objects: obs_names\[1\] = None: object names must be str"):
        metrics.match_objects(["a", "b"], ["a", None], score)
    with pytest.raises(ValueError, match=r"match_objects: obs_names\[0\] = 3: object names must be str"):
        metrics.match_objects(None, [3, "c"], score)
    assert metrics.match_objects(np.array(["a", "b"]), ("a", "c"), score) == [(0, 0)]


def test_default_names_are_not_identities():
    """Two boxes listed in the other order: with default names (what parse gives unnamed objects, and what
    generated scenes carry) they pair by overlap / position, so swapping the list costs nothing; with chosen names
    the names still decide."""
    obs = _seg([[0, 0, 1, 1]])
    pred = _seg([[1, 1, 0, 0]])
    default = ("box_0", "box_1")
    assert metrics.segmentation_iou(pred, obs, pred_names=default, obs_names=default) == (1.0, 1.0)
    assert metrics.segmentation_iou(pred, obs, pred_names=("a", "b"), obs_names=("a", "b")) == (0.0, 0.0)
    # a chosen name pairs first, the default-named rest by overlap
    score = np.array([[0.0, 0.9, 0.0], [0.0, 0.0, 0.7], [0.6, 0.0, 0.0]])
    assert metrics.match_objects(["a", "box_0", "box_1"], ["a", "box_0", "box_1"], score) == [(0, 0), (1, 2)]
    assert metrics.match_objects(["x", "box_0", "box_1"], ["a", "box_0", "box_1"], score) == [(0, 1), (1, 2), (2, 0)]
    assert [
        n
        for n in ("box_0", "sphere_12", "cylinder_3", "box", "box_a", "Box_0", "crate_0")
        if scenelib.is_default_name(n)
    ] == ["box_0", "sphere_12", "cylinder_3"]

    # state errors: unnamed boxes written in the other order are exact
    two = "- {{type: box, size: [0.2, 0.2, 0.2], state: {{position: [{}, 0, 0.1]}}}}\n"
    truth = _scene(two.format(0) + two.format(2))
    swapped = _scene(two.format(2) + two.format(0))
    assert truth.names == swapped.names == ("box_0", "box_1")
    assert metrics.state_mae(swapped, truth) == (0.0, 0.0)


def test_iou_union_subtracts_the_intersection_in_matching():
    """One 16-px row. Sizes: pred 0 = 3, pred 1 = 9, obs 0 = 7, obs 1 = 6 px; shared: (p0, o0) 2, (p1, o0) 5,
    (p1, o1) 2. Sequence IoUs: p0-o0 2/8, p1-o0 5/11, p1-o1 2/13, so the assignment takes p1-o0 (5/11 = 0.4545 >
    2/8 + 2/13 = 0.404) and drops p0-o1 (no overlap). Four objects visible, one pair counted once: 3 ->
    IoU = (5/11) / 3 = 5/33. (A union without the intersection taken off would prefer p0-o0 + p1-o1: 0.2019.)"""
    pred = _seg([[0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1, 1, -1, -1, -1, -1]])
    obs = _seg([[0, 0, -1, 0, 0, 0, 0, 0, 1, 1, -1, -1, 1, 1, 1, 1]])
    first, full = metrics.segmentation_iou(pred, obs)
    assert first == pytest.approx(5 / 33) and full == pytest.approx(5 / 33)


def test_composition_ignores_order():
    """The shapes are a multiset: [box, sphere] against [sphere, box] scores 1 on both counts."""
    box = "- {type: box, size: [0.2, 0.2, 0.2], state: {position: [1, 0, 0.2]}}\n"
    sphere = "- {type: sphere, radius: 0.2, state: {position: [0, 0, 0.2]}}\n"
    count, shapes = metrics.composition_accuracy([_scene(box + sphere)], [_scene(sphere + box)])
    assert count == [1.0] and shapes == [1.0]


def test_mean_finite_skips_nan_and_none():
    """mean of [1, nan, 3] over the finite values: 4 / 2 = 2; None and inf are skipped too; nothing finite: nan."""
    assert metrics.mean_finite([1.0, float("nan"), 3.0]) == 2.0
    assert metrics.mean_finite([None, 1.0, float("inf"), 3.0]) == 2.0
    assert np.isnan(metrics.mean_finite([float("nan")]))


def test_iou_named_predicted_object_never_visible():
    """Names ("a", "b") on both sides; the prediction only draws a (exactly over observed a), its b is nowhere, observed
    b is visible. No error: a scores 1, b 0 (paired by name, never visible on the predicted side); visible objects:
    predicted a, observed a and b, the pair counted once -> 2: IoU = 1 / 2."""
    pred = _seg([[0, 0, -1, -1]])
    obs = _seg([[0, 0, 1, 1]])
    first, full = metrics.segmentation_iou(pred, obs, pred_names=("a", "b"), obs_names=("a", "b"))
    assert first == pytest.approx(0.5) and full == pytest.approx(0.5)


def test_state_mae_pairs_chosen_names():
    """Observed a at x = 0, b at x = 3; predicted a at x = 3, b at x = 0: names pair a-a and b-b, each 3 m off in x
    -> position MAE (3 + 3) / (2 objects x 3 components) = 1.0 (by position they would pair at 0)."""
    obj = "- {{type: box, name: {}, size: [0.2, 0.2, 0.2], state: {{position: [{}, 0, 0.1]}}}}\n"
    obs = _scene(obj.format("a", 0) + obj.format("b", 3))
    pred = _scene(obj.format("a", 3) + obj.format("b", 0))
    assert metrics.state_mae(pred, obs) == pytest.approx((1.0, 0.0))


def test_iou_full_averages_every_frame_and_skips_a_pair_shown_by_neither_side():
    """Frame 0: a and b exact on both sides: (1 + 1) / 2 = 1. Frame 1: b has left both views; a is predicted at
    pixels {1, 2}, observed at {0, 1}: 1 / 3, and b, seen by neither side, neither scores nor counts: 1/3.
    first = 1, full = (1 + 1/3) / 2 = 2/3."""
    pred = _seg([[0, 0, 1, 1]], [[-1, 0, 0, -1]])
    obs = _seg([[0, 0, 1, 1]], [[0, 0, -1, -1]])
    np.testing.assert_allclose(metrics.iou_from_counts(metrics.overlap_counts(pred, obs, 2, 2)), [1.0, 1 / 3])
    first, full = metrics.segmentation_iou(pred, obs)
    assert first == 1.0 and full == pytest.approx(2 / 3)


def test_iou_of_a_prediction_without_any_object_pixel():
    """A prediction whose objects are all out of view (masks all -1, no names): the observed object is unmatched in
    frame 0 (0 / 1) and no object shows on either side in frame 1 (1): (0, 0.5); nothing on either side in any frame:
    (1, 1). Both raised "cannot reshape array of size 0" in the assignment's tie-break (`content_rank`)."""
    empty = _seg([[-1, -1]], [[-1, -1]])
    assert metrics.segmentation_iou(empty, _seg([[0, -1]], [[-1, -1]])) == (0.0, 0.5)
    assert metrics.segmentation_iou(empty, empty) == (1.0, 1.0)
    assert metrics.content_rank(np.zeros((0, 2, 1))).tolist() == []


def test_epe_is_zero_when_no_frame_shows_an_object():
    """No object on either side in any frame: nothing to get wrong, EPE (0, 0), not nan."""
    none = _seg([[-1, -1]], [[-1, -1]])
    flow = np.ones((2, 1, 2, 2))
    assert metrics.flow_epe(flow, np.zeros_like(flow), none, none) == (0.0, 0.0)


def test_state_mae_averages_absolute_components_not_distances():
    """One object 0.3 m off in x and 0.4 m in y (0.5 m away), velocity off by (0, 0.6, 0.8): MAE over the three
    components (0.3 + 0.4 + 0) / 3 = 0.7/3 m and (0.6 + 0.8) / 3 m/s (the distance / 3 would give 0.5/3 and 1/3)."""
    obs = _scene("- {type: sphere, radius: 0.2, state: {position: [0, 0, 0.2]}}\n")
    pred = _scene("- {type: sphere, radius: 0.2, state: {position: [0.3, 0.4, 0.2], linear_velocity: [0, 0.6, 0.8]}}\n")
    assert metrics.state_mae(pred, obs) == pytest.approx((0.7 / 3, 1.4 / 3))


def test_composition_shapes_are_a_multiset_not_a_set():
    """[box, box, sphere] against [box, sphere, sphere]: same count (1), same set of shapes, different multiset (0)."""
    box = "- {type: box, size: [0.2, 0.2, 0.2], state: {position: [1, 0, 0.2]}}\n"
    sphere = "- {type: sphere, radius: 0.2, state: {position: [0, 0, 0.2]}}\n"
    count, shapes = metrics.composition_accuracy([_scene(box * 2 + sphere)], [_scene(box + sphere * 2)])
    assert count == [1.0] and shapes == [0.0]


def test_state_mae_pairs_by_optimal_assignment_not_nearest():
    """Unnamed boxes observed at x = 0 and 1, predicted at x = 0.4 and 2. The assignment minimises the summed
    distance: p0-o0 + p1-o1 = 0.4 + 1.0 = 1.4 beats p0-o1 + p1-o0 = 0.6 + 2.0 = 2.6, so position MAE =
    (0.4 + 1.0) / (2 objects x 3 components) = 1.4 / 6. Pairing every observed object with its nearest prediction
    instead (both with p0: 0.4 and 0.6) would give 1.0 / 6 (the assignment's pairs must survive the zero-overlap
    filter: their scores are all negative)."""
    obj = "- {{type: box, size: [0.2, 0.2, 0.2], state: {{position: [{}, 0, 0.1]}}}}\n"
    truth = _scene(obj.format(0) + obj.format(1))
    pred = _scene(obj.format(0.4) + obj.format(2))
    assert metrics.state_mae(pred, truth) == pytest.approx((1.4 / 6, 0.0))


def test_state_mae_unpaired_video_object_takes_the_nearest_prediction():
    """Observed x = 0, 1, 5; predicted x = 5 (p0) and 0.4 (p1). The assignment pairs p0-o2 (0) and p1-o0 (0.4)
    (total 0.4; p1-o1 instead: 0.6). o1 is left over and meets its nearest prediction, p1 (0.6 m; p0 is 4 m away):
    position MAE (0 + 0.4 + 0.6) / 9 = 1 / 9 (with the first prediction instead: (0 + 0.4 + 4) / 9)."""
    obj = "- {{type: box, size: [0.2, 0.2, 0.2], state: {{position: [{}, 0, 0.1]}}}}\n"
    truth = _scene(obj.format(0) + obj.format(1) + obj.format(5))
    pred = _scene(obj.format(5) + obj.format(0.4))
    assert metrics.state_mae(pred, truth) == pytest.approx((1 / 9, 0.0))


def test_iou_pairs_objects_by_overlap_over_the_whole_sequence():
    """Observed: object 0 on columns {0, 1}, object 1 on {2, 3} in all 3 frames. Predicted: swapped in frame 0,
    right in frames 1 and 2. Sequence IoUs: p0-o0 = 4 / (6 + 6 - 4) = 0.5 = p1-o1; p0-o1 = 2 / (6 + 6 - 2) = 0.2
    = p1-o0: the straight pairing (1.0 > 0.4) holds. Frame 0 then scores 0 (both pairs miss, 2 visible pairs),
    frames 1 and 2 score 1: first = 0, full = 2/3. (Pairing by frame 0 alone would swap them: 1 and 1/3.)"""
    obs = _seg([[0, 0, 1, 1]], [[0, 0, 1, 1]], [[0, 0, 1, 1]])
    pred = _seg([[1, 1, 0, 0]], [[0, 0, 1, 1]], [[0, 0, 1, 1]])
    first, full = metrics.segmentation_iou(pred, obs)
    assert first == 0.0 and full == pytest.approx(2 / 3)


def test_metric_arguments_of_the_wrong_kind_are_named_not_failed_deep_inside():
    """match_objects: a 1-D, 3-D or NaN score matrix failed on tuple unpacking or inside scipy, and names past
    the matrix on list.remove; state_mae(str, str) on AttributeError; mismatched batches on zip's unnamed
    "argument 2 is shorter"; a YAML text as the prediction list was scored as 3 invalid characters; mean_finite
    of a str on a bare TypeError. A good call is unchanged: a (2, 2) score pairs (0, 1), (1, 0)."""
    with pytest.raises(ValueError, match=r"score has shape \(2,\)"):
        metrics.match_objects(None, None, np.array([0.5, 1.0]))
    with pytest.raises(ValueError, match=r"score has shape \(1, 2, 2\)"):
        metrics.match_objects(None, None, np.ones((1, 2, 2)))
    with pytest.raises(ValueError, match=r"score\[1, 0\] = nan: scores must be finite"):
        metrics.match_objects(None, None, np.array([[0.0, 1.0], [np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"pred_names = \['x', 'y', 'a'\]: must be a list of at most 2 names"):
        metrics.match_objects(["x", "y", "a"], ["a"], np.ones((2, 1)))
    assert metrics.match_objects(None, None, np.array([[0.0, 0.9], [0.8, 0.0]])) == [(0, 1), (1, 0)]
    obs = _scene("- {type: sphere, radius: 0.2, state: {position: [0, 0, 0.2]}}\n")
    with pytest.raises(TypeError, match=r"state_mae: pred is a str, not a Scene"):
        metrics.state_mae("- {type: sphere}", obs)
    with pytest.raises(TypeError, match=r"state_mae: obs is a NoneType, not a Scene"):
        metrics.state_mae(obs, None)
    with pytest.raises(ValueError, match=r"state_mae_batch: 2 predictions for 1 targets"):
        metrics.state_mae_batch([obs, obs], [obs])
    with pytest.raises(TypeError, match=r"state_mae_batch: predictions is a str"):
        metrics.state_mae_batch("abc", [obs, obs, obs])
    with pytest.raises(TypeError, match=r"composition_accuracy: targets\[0\] is a str"):
        metrics.composition_accuracy([obs], ["- {type: sphere}"])
    with pytest.raises(TypeError, match=r"mean_finite: values is a str"):
        metrics.mean_finite("abc")
    with pytest.raises(TypeError, match=r"mean_finite: values\[1\] = '2.0': must be a number or None"):
        metrics.mean_finite([1.0, "2.0"])
    assert metrics.mean_finite(x for x in (1.0, None, 3.0)) == 2.0


def test_equally_good_pairings_do_not_depend_on_the_list_order():
    """Ties of the assignment are broken by the objects, not by their places in the list.

    Masks: the video shows one object on columns {0, 1} in frames 0 and 1; the prediction draws it right with
    object A in frame 0 and with object B in frame 1 (each absent in the other frame). Sequence IoUs: A 2 / (2 + 4 -
    2) = 0.5 = B: a tie. Pairing A: frame 0 IoU 1, frame 1 B unmatched beside the observed object, 0 / 2 -> (1.0,
    0.5); pairing B: (0.0, 0.5). B's pixel counts (frame 0: none) sort before A's (frame 0: 2 on the object), so B
    is paired whichever comes first in the list: (0.0, 0.5) both ways (it was (1.0, 0.5) with A listed first).

    States: one sphere observed at x = 1 moving at 1 m/s, predicted at x = 0 (1 m/s) and x = 2 (still): both 1 m
    away. The first by state (x = 0) is paired whichever is listed first: position MAE 1 / 3, velocity 0 (it was
    1 / 3 with the still one listed first)."""
    obs = _seg([[0, 0, -1, -1]], [[0, 0, -1, -1]])
    a_first = _seg([[0, 0, -1, -1]], [[1, 1, -1, -1]])
    b_first = _seg([[1, 1, -1, -1]], [[0, 0, -1, -1]])
    assert metrics.segmentation_iou(a_first, obs) == metrics.segmentation_iou(b_first, obs) == (0.0, 0.5)
    assert metrics.content_rank([[0, 2, 0, 0], [0, 0, 0, 2], [0, 0, 0, 2]]).tolist() == [2, 0, 1]

    sphere = "- {{type: sphere, radius: 0.1, state: {{position: [{}, 0, 0.1], linear_velocity: [{}, 0, 0]}}}}\n"
    truth = _scene(sphere.format(1, 1))
    moving, still = sphere.format(0, 1), sphere.format(2, 0)
    assert metrics.state_mae(_scene(moving + still), truth) == pytest.approx((1 / 3, 0.0))
    assert metrics.state_mae(_scene(still + moving), truth) == pytest.approx((1 / 3, 0.0))
    with pytest.raises(ValueError, match=r"match_objects: pred_rank has 1 entries for 2 objects"):
        metrics.match_objects(None, None, np.ones((2, 2)), pred_rank=[0])
