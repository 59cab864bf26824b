"""The YOLOv3 baseline: boxes, anchors, targets, loss, reference post-processing, a few training steps,
export round trip (onnxruntime vs PyTorch, metadata) and the committed Rust fixture."""

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from gelstereo_train import yolo_eval, yolo_export, yolo_train
from gelstereo_train.augment import AugConfig, make_batch
from gelstereo_train.data import list_samples, median_nn_distance
from gelstereo_train.yolo_model import YoloV3, decode_head, kmeans_anchors, wh_iou
from gelstereo_train.yolo_post import YoloPost, postprocess

FIXTURES = Path(__file__).resolve().parents[2] / "data" / "fixtures" / "onnx"


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One thread: on a loaded 2-core machine two spinning threads make these tests ~50x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_marker_boxes_follow_the_local_lattice_spacing_per_axis():
    r, c = np.mgrid[0:4, 0:5]
    pts = np.stack([c.ravel() * 10.0, r.ravel() * 14.0], 1)  # x pitch 10, y pitch 14
    wh = yolo_train.marker_boxes(pts, 0.5)
    np.testing.assert_allclose(wh, np.tile([5.0, 7.0], (len(pts), 1)))
    # A lone marker has no spacing: NaN unless a fallback pitch is given.
    assert np.isnan(yolo_train.marker_boxes(pts[:1], 0.5)).all()
    np.testing.assert_allclose(yolo_train.marker_boxes(pts[:1], 0.5, fallback_px=12.0), [[6.0, 6.0]])
    # A single row: the missing vertical spacing takes the horizontal one.
    np.testing.assert_allclose(yolo_train.marker_boxes(pts[:5], 0.5), np.tile([5.0, 5.0], (5, 1)))


def test_dot_to_pitch_ratio_is_read_per_experiment(tmp_path):
    exp = tmp_path / "train" / "exp_0000"
    exp.mkdir(parents=True)
    (exp / "meta.json").write_text(json.dumps({"sensor": {"grid": {"pitch_mm": 1.0, "dot_diameter_mm": 0.35}}}))
    frac, src = yolo_train.diameter_fraction(exp)
    assert frac == pytest.approx(0.35) and src.endswith("meta.json")
    other = tmp_path / "train" / "exp_0001"
    other.mkdir()
    (other / "meta.json").write_text("{}")
    assert yolo_train.diameter_fraction(other)[0] == yolo_train.DEFAULT_DIAMETER_FRAC
    (tmp_path / "dataset.json").write_text(json.dumps({"grid": {"pitch_mm": 2.0, "dot_diameter_mm": 0.8}}))
    assert yolo_train.diameter_fraction(other)[0] == pytest.approx(0.4)


def test_kmeans_recovers_two_box_shapes():
    rng = np.random.default_rng(0)
    wh = np.concatenate([rng.normal([4, 6], 0.05, (200, 2)), rng.normal([8, 8], 0.05, (100, 2))])
    a = kmeans_anchors(wh, 2, seed=1)
    np.testing.assert_allclose(a, [[4, 6], [8, 8]], atol=0.05)
    assert wh_iou([[4, 6]], [[4, 6], [2, 6]]).tolist() == [[1.0, 0.5]]
    with pytest.raises(ValueError):
        kmeans_anchors(wh[:1], 2)


def test_targets_assign_best_anchor_and_fall_back_when_taken():
    anchors = np.array([[[4.0, 4.0], [6.0, 6.0]], [[8.0, 8.0], [12.0, 12.0]]])  # heads at strides 8, 16
    labels = [np.array([[3.0, 3.0], [5.0, 5.0], [20.0, 12.0]])]
    boxes = [np.array([[4.0, 4.0], [4.2, 4.2], [12.0, 12.0]])]
    tg = yolo_train.build_targets(labels, boxes, [(4, 4), (2, 2)], (8, 16), anchors, 32.0 * 32.0)
    assert tg.assigned == 3 and tg.fallbacks == 1 and tg.collisions == 0
    m8, m16 = tg.mask
    assert m8[0, 0, 0, 0] and m8[0, 0, 0, 1]  # both small markers in cell (0, 0): anchor 0, then 1
    assert m16[0, 0, 1, 1]  # the big one at stride 16, cell (gy 0, gx 1), anchor 12x12
    np.testing.assert_allclose(tg.txy[0][0, 0, 0, 0].numpy(), [3 / 8, 3 / 8])
    np.testing.assert_allclose(tg.twh[0][0, 0, 0, 1].numpy(), np.log([4.2 / 6.0, 4.2 / 6.0]), rtol=1e-6)
    np.testing.assert_allclose(tg.txy[1][0, 0, 1, 1].numpy(), [20 / 16 - 1, 12 / 16])


def test_local_ignore_mask_equals_the_brute_force_one():
    torch.manual_seed(1)
    rng = np.random.default_rng(1)
    anchors = torch.tensor([[5.0, 6.0], [7.0, 7.0]])
    dec = decode_head(torch.randn(2, 6, 8, 2, 5) * 0.5, 8, anchors)
    gt = [np.c_[rng.uniform(0, 64, (30, 1)), rng.uniform(0, 48, (30, 1)), rng.uniform(4, 8, (30, 2))].astype(np.float32),
          np.zeros((0, 4), np.float32)]
    got = yolo_train.ignore_mask(dec, gt, 8, 0.3)
    want = torch.zeros(2, 6, 8, 2, dtype=torch.bool)
    want[0] = (yolo_train.box_iou_xywh(dec[0, ..., :4].reshape(-1, 4), torch.from_numpy(gt[0])).max(1).values
               > 0.3).view(6, 8, 2)
    assert want.sum() > 5
    assert torch.equal(got, want)


def test_reference_decoding_matches_the_torch_decoding():
    torch.manual_seed(0)
    model = YoloV3(np.array([[[4, 5], [5, 6]], [[7, 8], [9, 9]]]), strides=(8, 16), width=2).eval()
    x = torch.rand(1, 3, 32, 64)
    with torch.no_grad():
        raw = model(x)[0].numpy()
        maps = model.head_maps(x)
        ref = torch.cat([decode_head(m, s, a).reshape(1, -1, 5)
                         for m, s, a in zip(maps, model.strides, model.anchors)], 1)[0].numpy()
    # all boxes (threshold below any objectness) of an image the size of the input: x = x_in - 0.5
    every = YoloPost(conf_threshold=-1.0, nms_iou=1.0)
    dec = postprocess(raw, (32, 64), (8, 16), model.anchors.numpy(), (64, 32), every)["candidates"]
    np.testing.assert_allclose(dec + [0.5, 0.5, 0, 0, 0], ref, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="raw: expected shape"):
        postprocess(raw[:-1], (32, 64), (8, 16), model.anchors.numpy(), (64, 32), every)


def test_nms_keeps_the_best_of_overlapping_boxes():
    # one stride-32 head of one 4 x 4 px anchor on a 64 x 32 input: the boxes of cells (0, 0) and
    # (0, 1) lie 1 px apart across the cells' border (IoU 0.6)
    logit = lambda p: float(np.log(p / (1 - p)))  # noqa: E731
    raw = np.full((2, 5), -20.0, np.float32)
    raw[0] = [logit(31.5 / 32), 0.0, 0.0, 0.0, logit(0.8)]
    raw[1] = [logit(0.5 / 32), 0.0, 0.0, 0.0, logit(0.9)]
    args = ((32, 64), (32,), np.array([[[4.0, 4.0]]]), (64, 32))
    kept = postprocess(raw, *args, YoloPost(0.1, 0.45))["markers"]
    assert kept[:, 2].tolist() == pytest.approx([0.9])
    assert postprocess(raw, *args, YoloPost(0.1, 0.95))["markers"][:, 2].tolist() == pytest.approx([0.9, 0.8])


def test_loss_falls_on_a_fixed_batch(tiny_root):
    torch.manual_seed(0)
    s = list_samples(tiny_root, "train")
    imgs = [a.load() for a in s]
    pts = [a.points_px for a in s]
    x, labels = make_batch(imgs, pts, np.array([median_nn_distance(p) for p in pts]), 4,
                           AugConfig(crop=(64, 64), input_size=(128, 128)), np.random.default_rng(0))
    boxes = [yolo_train.marker_boxes(lab, 0.5) for lab in labels]
    anchors = np.array([[[4.0, 5.0], [5.0, 6.0]], [[6.0, 7.0], [7.0, 8.0]]])
    model = YoloV3(anchors, strides=(8, 16), width=4)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        maps = model.head_maps(x)
        tg = yolo_train.build_targets(labels, boxes, [m.shape[1:3] for m in maps], (8, 16), anchors, 64.0 * 64.0)
        loss = yolo_train.yolo_loss(maps, tg, (8, 16), model.anchors)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert tg.assigned > 10
    assert losses[-1] < 0.5 * losses[0]


def test_train_export_round_trip_and_evaluation(tiny_root, tmp_path):
    ck = tmp_path / "yolo.pt"
    args = yolo_train.parser().parse_args(
        ["--data", str(tiny_root), "--out", str(ck), "--steps", "3", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "2"]
    )
    yolo_train.train(args, log=lambda *_: None)
    out = tmp_path / "yolo.onnx"
    report = tmp_path / "report.json"
    assert yolo_export.main(["--checkpoint", str(ck), "--out", str(out), "--conf-threshold", "0.3",
                             "--report", str(report)]) == 0
    assert json.loads(report.read_text())["max_abs_diff"] < 1e-4
    m = onnx.load(str(out))
    meta = {p.key: p.value for p in m.metadata_props}
    assert meta["contract"] == "gelstereo-yolo/1"
    assert (meta["strides"], meta["anchors_per_head"], meta["conf_threshold"]) == ("8,16", "3", "0.3")
    assert len(yolo_export.parse_anchors(meta["anchors"])) == 6
    assert [i.name for i in m.graph.input] == ["image"] and [o.name for o in m.graph.output] == ["raw"]
    assert m.opset_import[0].version == 17
    # The same model evaluated as checkpoint and as ONNX gives the same metrics.
    samples = list_samples(tiny_root, "val")[:2]
    a = yolo_eval.evaluate(samples, yolo_eval.YoloRunner(ck), [0.3], 0.45, log=lambda *_: None)
    b = yolo_eval.evaluate(samples, yolo_eval.YoloRunner(out), [0.3], 0.45, log=lambda *_: None)
    assert a["thresholds"]["0.3"]["all"]["T"] > 0
    for split in ("all", "easy", "hard", "contact"):
        for k in ("T", "PT", "PF"):
            assert a["thresholds"]["0.3"][split][k] == b["thresholds"]["0.3"][split][k], (split, k)
    assert a["best"] == 0.3


def test_committed_rust_fixture_is_consistent():
    fx = json.loads((FIXTURES / "yolo_tiny_expected.json").read_text())
    raw = np.asarray(fx["raw"], np.float32).reshape(fx["raw_shape"])
    res = postprocess(raw, (fx["input_height"], fx["input_width"]), fx["strides"], np.asarray(fx["anchors"]),
                      (fx["image_width"], fx["image_height"]), YoloPost(fx["conf_threshold"], fx["nms_iou"]))
    np.testing.assert_allclose(res["markers"], fx["markers"], atol=1e-12)
    assert len(fx["candidates"]) > len(fx["markers"]) > 0
    sess = ort.InferenceSession(str(FIXTURES / "yolo_tiny.onnx"), providers=["CPUExecutionProvider"])
    meta = sess.get_modelmeta().custom_metadata_map
    np.testing.assert_array_equal(yolo_export.parse_anchors(meta["anchors"]), np.asarray(fx["anchors"]))
    assert float(meta["conf_threshold"]) == fx["conf_threshold"]
    sizes = sum((FIXTURES / f).stat().st_size for f in ("yolo_tiny.onnx", "yolo_tiny_expected.json", fx["image"]))
    assert sizes < 200_000
