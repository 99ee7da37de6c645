"""DepthModel on the tiny random-weight Depth Anything V2 reference networks (MOMA_SHARED_DIR/
reference/dav2; see its README). Their outputs mean nothing: this checks the plumbing and
parity with the official PyTorch code, not depth quality."""

import json
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import moma
from conftest import shared_dir

SHARED = shared_dir()
REF = SHARED / "reference" / "dav2" if SHARED else None
pytestmark = pytest.mark.skipif(
    REF is None or not (REF / "tiny-metric.safetensors").is_file(),
    reason="Depth Anything reference data not found: set MOMA_SHARED_DIR (needs reference/dav2)",
)


def tiny_config(name):
    """The tiny networks' architecture (as crates/moma-depth/tests/common/mod.rs builds it)."""
    meta = json.loads((REF / f"{name}.json").read_text())
    head = (
        {"head": "metric", "max_depth_m": meta["max_depth"]}
        if meta["head"] == "metric"
        else {"head": "relative"}
    )
    return {
        "backbone": "vits",
        "embed_dim": 64,
        "depth": 4,
        "num_heads": 2,
        "mlp_hidden_dim": 256,
        "intermediate_layers": [0, 1, 2, 3],
        "features": 16,
        "out_channels": [8, 16, 32, 64],
        "head": head,
        "input_size": meta["input_size"],
        "pos_grid": 37,
        "layer_norm_eps": 1e-6,
    }


def read_png_rgb(_=None):
    """The reference image (640×480 RGB) through moma's own reader."""
    return moma.read_rgb(REF / "input.png")


@pytest.fixture(scope="module")
def tiny_metric():
    return moma.DepthModel(REF / "tiny-metric.safetensors", config=tiny_config("tiny-metric"))


def test_metric_head_kind_and_output(tiny_metric):
    assert tiny_metric.kind == "metric-depth"
    assert tiny_metric.runtime.lower().startswith("candle, cpu")
    rgb = read_png_rgb()
    pred = tiny_metric.predict(rgb)
    assert pred.dtype == np.float32 and pred.shape == (480, 640)
    assert np.isfinite(pred).all()
    # metric head: Sigmoid × max_depth → strictly inside (0, 20) metres
    assert pred.min() > 0.0 and pred.max() < 20.0


@pytest.mark.parametrize("name", ["tiny-metric", "tiny-rel-392"])
def test_matches_official_pytorch_reference(name):
    """Full path (pre-processing, network, resize back) against the official code's output."""
    m = moma.DepthModel(REF / f"{name}.safetensors", config=tiny_config(name))
    pred = m.predict(moma.read_rgb(REF / "input.png"))
    want = np.load(REF / f"{name}.output_full.npy")
    assert pred.shape == want.shape == (480, 640)
    rel = np.abs(pred - want).max() / (want.max() - want.min())
    assert rel < 1e-3, rel


def test_relative_head_kind():
    m = moma.DepthModel(REF / "tiny-rel.safetensors", config=tiny_config("tiny-rel"))
    assert m.kind == "relative-disparity"
    pred = m.predict(read_png_rgb()[:100, :150].copy())
    assert pred.shape == (100, 150) and (pred >= 0).all()  # ReLU head


def test_predict_from_worker_threads_is_deterministic(tiny_metric):
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 256, (98, 130, 3), dtype=np.uint8) for _ in range(4)]
    serial = [tiny_metric.predict(i) for i in imgs]
    with ThreadPoolExecutor(max_workers=3) as pool:
        par = list(pool.map(tiny_metric.predict, imgs))
    for a, b in zip(serial, par):
        np.testing.assert_array_equal(a, b)


def test_predict_then_calibrate_and_align(tiny_metric):
    rgb = read_png_rgb()[:140, :182].copy()
    pred = tiny_metric.predict(rgb)
    gt = (0.5 * pred + 0.1).astype(np.float32)
    cal = moma.calibrate(pred, gt, kind=tiny_metric.kind, method="gssa", norm="none")
    np.testing.assert_allclose(cal.align(pred), gt, rtol=1e-4, atol=1e-5)


def test_bad_model_inputs(tiny_metric):
    with pytest.raises(moma.InvalidInputError, match="uint8"):
        tiny_metric.predict(np.zeros((50, 50, 3), np.float32))
    with pytest.raises(moma.InvalidInputError, match="3-D"):
        tiny_metric.predict(np.zeros((50, 50), np.uint8))
    with pytest.raises(moma.MomaFileError, match="no such file"):
        moma.DepthModel(REF / "missing.safetensors")
    with pytest.raises(moma.MomaFileError):  # a ViT-S architecture does not fit tiny weights
        moma.DepthModel(REF / "tiny-metric.safetensors", model="vits", head="metric")
    with pytest.raises(moma.InvalidInputError, match="unknown model"):
        moma.DepthModel(REF / "tiny-metric.safetensors", model="vitx")
    with pytest.raises(moma.InvalidInputError, match="multiple of 14"):
        moma.DepthModel(REF / "tiny-metric.safetensors", input_size=500)
    with pytest.raises(moma.InvalidInputError, match="at most 4200"):
        moma.DepthModel(REF / "tiny-metric.safetensors", input_size=140_000)
    with pytest.raises(moma.MomaFileError, match="adapter.safetensors"):
        moma.DepthModel(REF / "tiny-metric.safetensors", lora="adapter.safetensors")


@pytest.mark.skipif(moma.has_onnx(), reason="this build has the ONNX backend")
def test_onnx_backend_absent_is_a_clear_error():
    with pytest.raises(moma.BackendError, match="without the ONNX Runtime backend"):
        moma.DepthModel(REF / "tiny-metric.onnx", backend="onnx")


def test_an_explicit_input_size_applies_to_a_config_model():
    """`input_size=` wins over the config dict's own, as `finetune(config=…, input_size=…)` and
    the CLI take it; without it the dict's applies (the reference parity above relies on it)."""
    cfg = tiny_config("tiny-metric")
    assert cfg["input_size"] != 56
    rgb = read_png_rgb()
    small = moma.DepthModel(REF / "tiny-metric.safetensors", config=cfg, input_size=56).predict(rgb)
    own = moma.DepthModel(REF / "tiny-metric.safetensors", config=cfg).predict(rgb)
    same = moma.DepthModel(
        REF / "tiny-metric.safetensors", config=cfg, input_size=cfg["input_size"]
    ).predict(rgb)
    assert small.shape == own.shape == (480, 640)
    assert np.array_equal(own, same)
    assert not np.allclose(small, own)
    with pytest.raises(moma.InvalidInputError, match="input_size=-1"):
        moma.DepthModel(REF / "tiny-metric.safetensors", config=cfg, input_size=-1)


def test_a_config_fixes_the_network_and_its_head():
    """A `config` dict is the network, head included, as `--model PATH.json` is for the CLI:
    `model=` beside it and a disagreeing `head=` / `max_depth=` are refused (they were ignored,
    and the dict's head ran); agreeing ones are accepted and give the same model."""
    w = REF / "tiny-metric.safetensors"
    cfg = tiny_config("tiny-metric")
    own_max = cfg["head"]["max_depth_m"]
    for kwargs, says in [
        ({"model": "vitb"}, "model='vitb' and config= both name the network"),
        ({"head": "relative"}, "head='relative' disagrees with the metric head of config="),
        ({"max_depth": own_max + 0.5}, f"max_depth={own_max + 0.5} disagrees with config="),
    ]:
        with pytest.raises(moma.InvalidInputError, match=says):
            moma.DepthModel(w, config=cfg, **kwargs)
        if "max_depth" not in kwargs:  # lora_fingerprint has no max_depth
            with pytest.raises(moma.InvalidInputError, match=says):
                moma.lora_fingerprint(w, config=cfg, **kwargs)
    rel = tiny_config("tiny-rel")
    with pytest.raises(moma.InvalidInputError, match="head='metric' disagrees with the relative head"):
        moma.DepthModel(REF / "tiny-rel.safetensors", config=rel, head="metric")
    rgb = read_png_rgb()
    agreeing = moma.DepthModel(w, config=cfg, head="metric", max_depth=own_max).predict(rgb)
    assert np.array_equal(agreeing, moma.DepthModel(w, config=cfg).predict(rgb))
