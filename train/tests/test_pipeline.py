"""Train a few steps on the tiny dataset, build the MRE set, export both models and check them in
onnxruntime against PyTorch (the export round trip of the issue)."""

import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from gelstereo_train import evaluate, export, train_marknet, train_mre
from gelstereo_train.augment import AugConfig, make_batch
from gelstereo_train.data import list_samples, median_nn_distance
from gelstereo_train.loss import build_targets, distillation_loss, marknet_loss
from gelstereo_train.model import Marknet


def test_training_reduces_the_loss_on_a_fixed_batch(tiny_root):
    torch.manual_seed(0)
    s = list_samples(tiny_root, "train")
    imgs = [a.load() for a in s]
    pts = [a.points_px for a in s]
    rng = np.random.default_rng(0)
    x, labels = make_batch(imgs, pts, np.array([median_nn_distance(p) for p in pts]), 4,
                           AugConfig(crop=(96, 96), input_size=(128, 128)), rng)
    m = Marknet(stride=8, candidates=2, width=4)
    opt = torch.optim.Adam(m.parameters(), lr=1e-2)
    losses = []
    for _ in range(40):
        raw = m(x)
        tgt, mask, _ = build_targets(labels, raw.shape[1], raw.shape[2], 8, 2)
        loss = marknet_loss(raw, tgt, mask, 8)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


@pytest.fixture(scope="module")
def trained(tiny_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    ck = out / "marknet.pt"
    args = train_marknet.parser().parse_args(
        ["--data", str(tiny_root), "--out", str(ck), "--steps", "3", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "4", "--candidates", "3"]
    )
    train_marknet.train(args, log=lambda *_: None)
    mre = out / "mre.pt"
    assert train_mre.main(["--data", str(tiny_root), "--marknet", str(ck), "--out", str(mre), "--epochs", "2",
                           "--variants", "1"]) == 0
    onnx_dir = out / "onnx"
    assert export.main(["--marknet", str(ck), "--mre", str(mre), "--out-dir", str(onnx_dir)]) == 0
    return ck, mre, onnx_dir


def test_export_round_trip_and_metadata(trained):
    ck, mre_ck, onnx_dir = trained
    report = json.loads((onnx_dir / "export_report.json").read_text())
    # tolerance: float32 ONNX Runtime vs PyTorch with folded BatchNorm
    assert report["marknet_max_abs_diff"] < 1e-4 and report["mre_max_abs_diff"] < 1e-5
    m = onnx.load(str(onnx_dir / "marknet.onnx"))
    props = {p.key: p.value for p in m.metadata_props}
    assert props["contract"] == "gelstereo-marknet/2" and props["input_size"] == "dynamic"
    assert (props["input_multiple"], props["pitch_range_px"], props["pitch_target_px"]) == ("32", "9,24", "12")
    assert (props["input_height"], props["input_width"], props["stride"], props["grid"], props["candidates"]) == (
        "128", "128", "8", "16", "3")
    assert props["normalisation"] == "rgb/255" and props["layout"] == "NCHW" and "images=" in props["dataset"]
    assert m.opset_import[0].version == 17
    sess = ort.InferenceSession(str(onnx_dir / "marknet.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["image"] and [o.name for o in sess.get_outputs()] == ["raw"]
    model, _ = train_marknet.load_checkpoint(ck)
    for n, h, w in ((1, 128, 128), (3, 128, 128), (2, 96, 160)):  # dynamic batch, height and width
        x = torch.rand(n, 3, h, w)
        got = sess.run(["raw"], {"image": x.numpy()})[0]
        with torch.no_grad():
            ref = model(x).numpy()
        assert got.shape == (n, h // 8, w // 8, 3, 3)
        assert np.abs(got - ref).max() < 1e-4
    mprops = {p.key: p.value for p in onnx.load(str(onnx_dir / "mre.onnx")).metadata_props}
    assert mprops["contract"] == "gelstereo-mre/1" and mprops["features"] == "11" and mprops["accept"] == "0.99"
    ms = ort.InferenceSession(str(onnx_dir / "mre.onnx"), providers=["CPUExecutionProvider"])
    f = np.random.default_rng(0).uniform(0, 4, (5, 11)).astype(np.float32)
    score = ms.run(["score"], {"features": f})[0]
    ref = evaluate.load_mre(mre_ck)(f)
    assert score.shape == (5, 1) and np.abs(score[:, 0] - ref).max() < 1e-5


def test_evaluate_runs_on_onnx_and_checkpoint_alike(trained, tiny_root, tmp_path):
    ck, mre_ck, onnx_dir = trained
    out = tmp_path / "eval.json"
    assert evaluate.main(["--data", str(tiny_root), "--split", "test", "--marknet", str(onnx_dir / "marknet.onnx"),
                          "--mre", str(onnx_dir / "mre.onnx"), "--out", str(out)]) == 0
    a = json.loads(out.read_text())
    assert evaluate.main(["--data", str(tiny_root), "--split", "test", "--marknet", str(ck), "--mre", str(mre_ck),
                          "--out", str(out)]) == 0
    b = json.loads(out.read_text())
    for method in ("marknet", "marknet_mre", "blob"):
        assert a[method]["all"]["T"] == b[method]["all"]["T"] > 0
        assert a[method]["all"]["PT"] == b[method]["all"]["PT"]
    # the blob baseline finds the clean rendered dots
    assert a["blob"]["easy"]["recall"] > 0.9


def test_warm_start_continues_from_a_checkpoint_of_the_same_architecture(trained, tiny_root, tmp_path):
    ck, _, _ = trained
    base = ["--data", str(tiny_root), "--steps", "1", "--lr", "0", "--batch", "2", "--crop", "64",
            "--input-size", "128", "--candidates", "3"]
    out = tmp_path / "warm.pt"
    train_marknet.train(train_marknet.parser().parse_args(base + ["--out", str(out), "--width", "4",
                                                                   "--init", str(ck)]), log=lambda *_: None)
    warm, meta = train_marknet.load_checkpoint(out)
    start, start_meta = train_marknet.load_checkpoint(ck)
    # One step at learning rate 0: the weights are the checkpoint's (BatchNorm statistics move), and the
    # record names where they came from.
    for (k, a), b in zip(warm.named_parameters(), start.parameters()):
        assert torch.equal(a, b), k
    assert meta["init"]["path"] == str(ck) and meta["init"]["steps"] == start_meta["steps"] == 3
    # Another architecture is refused with the difference named.
    with pytest.raises(SystemExit, match="width"):
        train_marknet.train(train_marknet.parser().parse_args(base + ["--out", str(tmp_path / "x.pt"), "--width",
                                                                       "8", "--init", str(ck)]), log=lambda *_: None)


def test_an_s4_checkpoint_warm_starts_the_bare_stem_and_not_the_reverse(tiny_root, tmp_path):
    base = ["--data", str(tiny_root), "--steps", "1", "--batch", "2", "--crop", "64", "--input-size", "128",
            "--candidates", "3", "--width", "4", "--save-every-min", "0"]
    s4 = tmp_path / "s4.pt"
    train_marknet.train(train_marknet.parser().parse_args(base + ["--out", str(s4), "--stem", "s4"]),
                        log=lambda *_: None)
    bare = tmp_path / "bare.pt"
    train_marknet.train(train_marknet.parser().parse_args(
        base + ["--out", str(bare), "--stem", "s4-bare", "--lr", "0", "--init", str(s4)]), log=lambda *_: None)
    start, _ = train_marknet.load_checkpoint(s4)
    warm, meta = train_marknet.load_checkpoint(bare)
    # Every weight of the bare model is the s4 checkpoint's; only the stride-4 residual block is left out.
    theirs = dict(start.named_parameters())
    for k, a in warm.named_parameters():
        assert torch.equal(a, theirs[k]), k
    assert meta["init"]["left_out"] and all(k.startswith("s4.1.") for k in meta["init"]["left_out"])
    assert len(list(warm.parameters())) < len(list(start.parameters()))
    # The bare model lacks the block s4 needs: refused, naming the stem.
    with pytest.raises(SystemExit, match="stem"):
        train_marknet.train(train_marknet.parser().parse_args(
            base + ["--out", str(tmp_path / "x.pt"), "--stem", "s4", "--init", str(bare)]), log=lambda *_: None)


def test_a_3x3_fusing_checkpoint_warm_starts_a_1x1_one_with_its_kernels_summed(tiny_root, tmp_path):
    base = ["--data", str(tiny_root), "--steps", "1", "--batch", "2", "--crop", "64", "--input-size", "128",
            "--candidates", "3", "--width", "4", "--save-every-min", "0", "--stem", "s4-bare"]
    wide = tmp_path / "wide.pt"
    train_marknet.train(train_marknet.parser().parse_args(base + ["--out", str(wide)]), log=lambda *_: None)
    narrow = tmp_path / "narrow.pt"
    train_marknet.train(train_marknet.parser().parse_args(
        base + ["--out", str(narrow), "--fuse-kernel", "1", "--lr", "0", "--init", str(wide)]), log=lambda *_: None)
    start, _ = train_marknet.load_checkpoint(wide)
    warm, _ = train_marknet.load_checkpoint(narrow)
    assert warm.arch()["fuse_kernel"] == 1 and "fuse_kernel" not in start.arch()
    theirs = dict(start.named_parameters())
    narrowed = 0
    for k, a in warm.named_parameters():
        if a.shape == theirs[k].shape:
            assert torch.equal(a, theirs[k]), k
        else:
            # Each 3x3 fusing kernel became the sum of its taps: the same answer to a constant input.
            assert a.shape[2:] == (1, 1) and theirs[k].shape[2:] == (3, 3), k
            assert torch.allclose(a, theirs[k].sum(dim=(2, 3), keepdim=True)), k
            narrowed += 1
    assert narrowed == len(warm.up)
    # The narrow model cannot warm-start the wide one: refused.
    with pytest.raises(SystemExit, match="architecture"):
        train_marknet.train(train_marknet.parser().parse_args(
            base + ["--out", str(tmp_path / "x.pt"), "--init", str(narrow)]), log=lambda *_: None)


def test_a_student_trained_on_the_teacher_alone_moves_towards_its_outputs(trained, tiny_root, tmp_path):
    # A teacher whose head says something else than a fresh network's prior (every slot ~0.02).
    teacher, meta = train_marknet.load_checkpoint(trained[0])
    with torch.no_grad():
        teacher.head.weight.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(3))
        teacher.head.bias.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(4))
    teacher_ck = tmp_path / "teacher.pt"
    train_marknet.save_checkpoint(teacher_ck, teacher, meta)
    s = list_samples(tiny_root, "train")
    imgs, pts = [a.load() for a in s], [a.points_px for a in s]
    x, _ = make_batch(imgs, pts, np.array([median_nn_distance(p) for p in pts]), 4,
                      AugConfig(crop=(64, 64), input_size=(128, 128)), np.random.default_rng(5))
    base = ["--data", str(tiny_root), "--batch", "2", "--crop", "64", "--input-size", "128", "--width", "4",
            "--seed", "7", "--save-every-min", "0", "--teacher", str(teacher_ck)]
    # No label loss (alpha = beta = 0): whatever the student learns comes from the teacher.
    student = {}
    for steps in ("1", "20"):
        out = tmp_path / f"student{steps}.pt"
        train_marknet.train(train_marknet.parser().parse_args(
            base + ["--candidates", "3", "--out", str(out), "--steps", steps, "--lr", "0.5", "--alpha", "0",
                    "--beta", "0"]),
            log=lambda *_: None)
        student[steps], _ = train_marknet.load_checkpoint(out)
    with torch.no_grad():
        want = teacher(x)
        before = float(distillation_loss(student["1"](x), want, 8)[0])
        after = float(distillation_loss(student["20"](x), want, 8)[0])
    assert after < 0.5 * before, (before, after)
    # A teacher with another head is refused, naming it.
    with pytest.raises(SystemExit, match="candidates"):
        train_marknet.train(train_marknet.parser().parse_args(
            base + ["--candidates", "2", "--out", str(tmp_path / "x.pt"), "--steps", "1"]), log=lambda *_: None)


def test_warm_start_from_an_exported_onnx_reproduces_it(trained, tiny_root, tmp_path):
    _, _, onnx_dir = trained
    base = ["--data", str(tiny_root), "--steps", "1", "--lr", "0", "--batch", "2", "--crop", "64",
            "--input-size", "128", "--candidates", "3", "--width", "4", "--save-every-min", "0"]
    out = tmp_path / "from_onnx.pt"
    train_marknet.train(train_marknet.parser().parse_args(
        base + ["--out", str(out), "--init", str(onnx_dir / "marknet.onnx")]), log=lambda *_: None)
    model, meta = train_marknet.load_checkpoint(out)
    # BatchNorm folded into the exported convolutions is re-inflated: the checkpoint computes the
    # exported function (one step at learning rate 0 moves only the BatchNorm statistics a little).
    assert meta["init"]["onnx"] and meta["init"]["max_abs_diff_vs_onnx"] < 1e-3
    x = torch.rand(1, 3, 96, 128)
    sess = ort.InferenceSession(str(onnx_dir / "marknet.onnx"), providers=["CPUExecutionProvider"])
    ref = sess.run(None, {"image": x.numpy()})[0]
    with torch.no_grad():
        got = model(x).numpy()
    assert np.abs(got - ref).max() < 0.05 * (np.abs(ref).max() + 1)
    # Another architecture is refused by name.
    with pytest.raises(SystemExit, match="convolution|stem|width"):
        train_marknet.train(train_marknet.parser().parse_args(
            base[:-6] + ["--width", "8", "--save-every-min", "0", "--out", str(tmp_path / "x.pt"),
                         "--init", str(onnx_dir / "marknet.onnx")]), log=lambda *_: None)


def test_held_out_families_leave_training_and_select_evaluation(tiny_root, tmp_path):
    import shutil

    root = tmp_path / "fam"
    shutil.copytree(tiny_root, root)
    exps = sorted(p for p in (root / "train").iterdir() if p.is_dir())
    meta = json.loads((exps[0] / "meta.json").read_text()) if (exps[0] / "meta.json").exists() else {}
    meta["families"] = ["marker:hue", "lattice:square"]
    (exps[0] / "meta.json").write_text(json.dumps(meta))
    logs = []
    args = train_marknet.parser().parse_args(
        ["--data", str(root), "--out", str(tmp_path / "m.pt"), "--steps", "1", "--batch", "2", "--crop", "64",
         "--input-size", "128", "--width", "4", "--candidates", "3", "--exclude-family", "marker:hue"])
    train_marknet.train(args, log=logs.append)
    left_out = [m for m in logs if "held out families" in m]
    n_first = len([s for s in list_samples(root, "train") if s.experiment == exps[0].name])
    assert left_out and f": {n_first} of " in left_out[0]
    # Holding out every training experiment is an error, not an empty run.
    for e in exps:
        m = json.loads((e / "meta.json").read_text()) if (e / "meta.json").exists() else {}
        (e / "meta.json").write_text(json.dumps(m | {"families": ["marker:hue"]}))
    with pytest.raises(SystemExit, match="held-out family"):
        train_marknet.train(args, log=lambda *_: None)
    (exps[0] / "meta.json").write_text('{"families": "marker:hue"}')
    from gelstereo_train.data import DatasetError, experiment_families
    with pytest.raises(DatasetError, match="families"):
        experiment_families(root, "train", exps[0].name)


def test_quantized_marknet_keeps_the_contract_and_the_float_ends(trained, tiny_root, tmp_path):
    from gelstereo_train import quantize

    _, _, onnx_dir = trained
    src = onnx_dir / "marknet.onnx"
    out = tmp_path / "marknet-int8.onnx"
    assert quantize.main(["--model", str(src), "--data", str(tiny_root), "--out", str(out), "--images", "4"]) == 0
    f, q = onnx.load(str(src)), onnx.load(str(out))
    fprops = {p.key: p.value for p in f.metadata_props}
    qprops = {p.key: p.value for p in q.metadata_props}
    assert qprops.pop("quantized").startswith("int8 static per-channel qdq percentile, 4 train-split inputs")
    assert qprops == fprops
    ops = [n.op_type for n in q.graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    # The stem reads the float input and the head writes float logits: no quantization at either end.
    consumers = [n.op_type for n in q.graph.node if "image" in n.input]
    producer = next(n for n in q.graph.node if "raw" in n.output)
    assert consumers == ["Conv"] and producer.op_type == "Transpose"
    x = torch.rand(2, 3, 96, 128).numpy()
    fs = ort.InferenceSession(str(src), providers=["CPUExecutionProvider"])
    qs = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    a, b = fs.run(["raw"], {"image": x})[0], qs.run(["raw"], {"image": x})[0]
    assert a.shape == b.shape and np.isfinite(b).all()
    assert np.abs(a - b).mean() < 0.1 * np.abs(a).mean() + 1e-3


def test_quantized_marknet_leaves_the_named_parts_in_float_and_refuses_unknown_ones(trained, tiny_root, tmp_path):
    from gelstereo_train import quantize

    _, _, onnx_dir = trained
    src = onnx_dir / "marknet.onnx"
    out = tmp_path / "marknet-int8.onnx"
    args = ["--model", str(src), "--data", str(tiny_root), "--out", str(out), "--images", "4"]
    assert quantize.main(args + ["--keep-float", "stem,head,decoder", "--method", "percentile"]) == 0
    q = onnx.load(str(out))
    assert {p.key: p.value for p in q.metadata_props}["quantized"].endswith("float: stem, head, decoder")
    # Float convolutions read float tensors straight from another float node, never a DequantizeLinear.
    made = {o: n.op_type for n in q.graph.node for o in n.output}
    decoder = [n for n in q.graph.node if n.op_type == "Conv" and n.name.startswith(("/fuse1/", "/fuse2/"))]
    backbone = [n for n in q.graph.node if n.op_type == "Conv" and n.name.startswith(("/s8/", "/s16/"))]
    assert decoder and backbone
    assert all(made.get(n.input[1]) != "DequantizeLinear" for n in decoder)
    assert all(made.get(n.input[1]) == "DequantizeLinear" for n in backbone)
    refused = tmp_path / "refused.onnx"
    with pytest.raises(SystemExit) as e:
        quantize.main(["--model", str(src), "--data", str(tiny_root), "--out", str(refused), "--keep-float", "stem,neck"])
    assert e.value.code == 2 and not refused.exists()


def test_histogram_calibration_crops_inputs_of_several_layouts_to_one_size():
    from gelstereo_train.quantize import cropped_to_common_size

    a = np.arange(2 * 3 * 64 * 96, dtype=np.float32).reshape(2, 3, 64, 96)[:1]
    b = np.zeros((1, 3, 96, 64), dtype=np.float32)
    ca, cb = cropped_to_common_size([a, b])
    assert ca.shape == cb.shape == (1, 3, 64, 64)
    # Cut about the centre: a's columns 16..79.
    assert np.array_equal(ca, a[:, :, :, 16:80]) and ca.flags["C_CONTIGUOUS"]


def test_averaged_checkpoints_hold_the_mean_weights_and_export(tmp_path):
    meta = {"input_height": 128, "input_width": 128, "dataset": "tiny", "trained": "t", "steps": 3,
            "aug": {"canonical": "auto"}}
    paths = []
    for seed in (1, 2):
        torch.manual_seed(seed)
        m = Marknet(stride=8, candidates=2, width=4)
        paths.append(tmp_path / f"m{seed}.pt")
        train_marknet.save_checkpoint(paths[-1], m, meta)
    soup, soup_meta = train_marknet.average_checkpoints(paths)
    a, _ = train_marknet.load_checkpoint(paths[0])
    b, _ = train_marknet.load_checkpoint(paths[1])
    for k, v in soup.state_dict().items():
        if v.is_floating_point():
            assert torch.allclose(v, (a.state_dict()[k] + b.state_dict()[k]) / 2), k
    assert [s["path"] for s in soup_meta["average_of"]] == [str(p) for p in paths]
    out = tmp_path / "soup.pt"
    train_marknet.save_checkpoint(out, soup, soup_meta)
    assert export.main(["--marknet", str(out), "--out-dir", str(tmp_path / "exp")]) == 0
    assert (tmp_path / "exp" / "marknet.onnx").is_file()


def test_checkpoints_of_other_architectures_are_not_averaged(tmp_path):
    meta = {"input_height": 128, "input_width": 128}
    paths = [tmp_path / "narrow.pt", tmp_path / "wide.pt"]
    train_marknet.save_checkpoint(paths[0], Marknet(stride=8, candidates=2, width=4), meta)
    train_marknet.save_checkpoint(paths[1], Marknet(stride=8, candidates=2, width=8), meta)
    with pytest.raises(SystemExit, match="wide.pt: architecture .* differs"):
        train_marknet.average_checkpoints(paths)
    with pytest.raises(SystemExit, match="no such checkpoint"):
        train_marknet.average_checkpoints([paths[0], tmp_path / "missing.pt"])
    torch.save({"weights": 1}, tmp_path / "other.pt")
    with pytest.raises(SystemExit, match="other.pt: not a Marknet checkpoint"):
        train_marknet.average_checkpoints([paths[0], tmp_path / "other.pt"])
