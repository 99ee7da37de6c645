"""`moma.finetune`: the fine-tuning run of `moma finetune`, from Python (issue 23), on the tiny
random-weight metric network (MOMA_SHARED_DIR/reference/dav2) and a shared moma set. Random
weights learn nothing meaningful: this checks that the two doors run the same training."""

import json
import subprocess

import numpy as np
import pytest

import moma
from conftest import moma_bin, shared_dir
from test_depth_model import tiny_config

SHARED = shared_dir()
REF = SHARED / "reference" / "dav2" if SHARED else None
SET = SHARED / "data" / "gqcnn-primesense" if SHARED else None
pytestmark = pytest.mark.skipif(
    REF is None or not (REF / "tiny-metric.safetensors").is_file() or not (SET / "camera.json").is_file(),
    reason="needs MOMA_SHARED_DIR with reference/dav2 and data/gqcnn-primesense",
)
BIN = moma_bin()

OPTS = dict(input_size=56, steps=6, lora_rank=2, lr=1e-3, seed=1, train_head=True, device="cpu", val_every=3)
# The CLI's spelling of OPTS.
CLI = ["--input-size", "56", "--steps", "6", "--lora-rank", "2", "--lr", "1e-3", "--seed", "1",
       "--train-head", "--device", "cpu", "--val-every", "3"]
TINY_JSON = {"embed_dim": 64, "depth": 4, "num_heads": 2, "intermediate_layers": [0, 1, 2, 3], "features": 16,
             "out_channels": [8, 16, 32, 64], "head": "metric", "max_depth": 20}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("ft") / "a.safetensors"
    cfg = tiny_config("tiny-metric")
    report = moma.finetune([SET], REF / "tiny-metric.safetensors", out, config=cfg, **OPTS)
    return cfg, out, report


def test_finetune_reports_what_the_reloaded_adapter_gives(trained):
    cfg, out, r = trained
    assert r["steps"] == 6 and r["loss"] == "silog" and r["adapter"] == str(out)
    assert r["train_frames"] + r["val_frames"] == 15
    assert abs(r["val_loss_after_reload"] - r["val_loss_after"]) <= 1e-5, r
    assert r["val_loss_after"] < r["val_loss_before"], r
    # every val_every validation, the last one at the final step: the trained network's loss
    assert [v["step"] for v in r["validations"]] == [3, 6], r
    assert r["validations"][-1]["loss"] == pytest.approx(r["val_loss_after"], rel=1e-6), r
    assert out.is_file() and out.with_suffix(".optim.safetensors").is_file()
    # The adapter, with its trained head, changes what DepthModel predicts.
    rgb = moma.read_rgb(REF / "input.png")
    weights = REF / "tiny-metric.safetensors"
    base = moma.DepthModel(weights, config=cfg, input_size=56).predict(rgb)
    tuned = moma.DepthModel(weights, config=cfg, input_size=56, lora=out).predict(rgb)
    assert np.abs(tuned - base).max() > 1e-3


@pytest.mark.skipif(BIN is None, reason="moma CLI not found: set MOMA_BIN or build it")
def test_python_and_cli_run_the_same_training(trained, tmp_path):
    """Same options, same seed: the same numbers and the same adapter, bit for bit."""
    _, out, r = trained
    cfg_json = tmp_path / "tiny.json"
    cfg_json.write_text(json.dumps(TINY_JSON))
    cli_out = tmp_path / "cli.safetensors"
    p = subprocess.run([BIN, "finetune", "--set", str(SET), "--weights", str(REF / "tiny-metric.safetensors"),
                        "--model", str(cfg_json), *CLI, "-o", str(cli_out), "--json"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    c = json.loads(p.stdout)
    assert set(c) == set(r)
    for k in r:
        if k not in ("step_time_s", "adapter"):
            assert c[k] == r[k], k
    from test_lora import read_safetensors
    a, b = read_safetensors(out), read_safetensors(cli_out)
    assert sorted(a) == sorted(b) and any(k.startswith("depth_head.") for k in a)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_the_cli_configuration_file_names_the_network_in_python(trained, tmp_path):
    """Issue 10's `--model PATH.json` file is accepted "in every command": in Python as
    `model="PATH.json"` or as its fields in `config=`, the same network as the internal dict
    (the same training, the same predictions). Both at once, or with a disagreeing head, are
    refused naming the file."""
    _, out, r = trained
    path = tmp_path / "tiny.json"
    path.write_text(json.dumps(TINY_JSON))
    w = REF / "tiny-metric.safetensors"
    by_file = moma.finetune([SET], w, tmp_path / "f.safetensors", model=str(path), **OPTS)
    for k in r:
        if k not in ("step_time_s", "adapter"):
            assert by_file[k] == r[k], k
    rgb = moma.read_rgb(REF / "input.png")
    want = moma.DepthModel(w, config=tiny_config("tiny-metric"), input_size=56, lora=out).predict(rgb)
    for kwargs in [dict(model=str(path)), dict(model=path), dict(config=TINY_JSON)]:
        got = moma.DepthModel(w, input_size=56, lora=out, **kwargs).predict(rgb)
        np.testing.assert_array_equal(got, want, err_msg=str(kwargs))
    with pytest.raises(moma.InvalidInputError, match="model='.*tiny.json' and config= both name"):
        moma.DepthModel(w, model=str(path), config=TINY_JSON)
    with pytest.raises(moma.InvalidInputError, match="head='relative' disagrees with the metric head of model="):
        moma.DepthModel(w, model=str(path), head="relative")
    with pytest.raises(moma.MomaFileError, match="missing.json"):
        moma.DepthModel(w, model=str(tmp_path / "missing.json"))
    with pytest.raises(moma.InvalidInputError, match="neither a DepthAnythingConfig"):
        moma.DepthModel(w, config={"embed_dim": 64})


def test_finetune_refuses_bad_options(tmp_path):
    cfg = tiny_config("tiny-metric")
    w = REF / "tiny-metric.safetensors"
    out = tmp_path / "x.safetensors"
    with pytest.raises(moma.InvalidInputError, match="steps or epochs"):
        moma.finetune([SET], w, out, config=cfg, input_size=56)
    with pytest.raises(moma.InvalidInputError, match="unknown LoRA target"):
        moma.finetune([SET], w, out, config=cfg, input_size=56, steps=1, lora_targets=["q", "x"])
    with pytest.raises(moma.InvalidInputError, match="ssi is for relative heads"):
        moma.finetune([SET], w, out, config=cfg, input_size=56, steps=1, loss="ssi")
    with pytest.raises(moma.InvalidInputError, match="head='relative' disagrees with the metric head"):
        moma.finetune([SET], w, out, config=cfg, head="relative", input_size=56, steps=1)
    with pytest.raises(moma.InvalidInputError, match="model='vits' and config= both name"):
        moma.finetune([SET], w, out, config=cfg, model="vits", input_size=56, steps=1)
    with pytest.raises(moma.MomaFileError, match="missing.safetensors"):
        moma.finetune([SET], tmp_path / "missing.safetensors", out, config=cfg, input_size=56, steps=1)
    assert not out.exists()


def test_ctrl_c_stops_finetune_without_writing(tmp_path):
    """Ctrl-C (a KeyboardInterrupt raised in the main thread) stops a long run at its next step:
    it raised only when the run ended, so a user waited out every step. Nothing is written."""
    import _thread
    import threading
    import time

    out = tmp_path / "a.safetensors"
    cfg = tiny_config("tiny-metric")
    opts = dict(OPTS, steps=1_000_000)
    timer = threading.Timer(2.0, _thread.interrupt_main)
    t0 = time.monotonic()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            moma.finetune([SET], REF / "tiny-metric.safetensors", out, config=cfg, **opts)
    finally:
        timer.cancel()
    assert time.monotonic() - t0 < 60, "stopped at the next step, not after the run"
    assert list(tmp_path.iterdir()) == [], "no adapter, no optimiser state"
