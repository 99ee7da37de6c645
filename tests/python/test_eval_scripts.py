"""The evaluation scripts of benches/eval on the CLI's JSON contract: `issue12_checks.py` runs
`moma eval --simulate --sim-seed S` on the shared sets (one simulator seed, one sampling seed:
a smoke run of every check, SIMULATED predictions) and `auto_rules.py`'s k-standard-error rule
on hand-made losses. Needs the `moma` binary ($MOMA_BIN or target/release/moma) and, for the
first, $MOMA_SHARED_DIR; skipped visibly without them."""

import importlib.util
import subprocess
import sys

import pytest

from conftest import REPO, moma_bin, shared_dir

BIN = moma_bin()
SHARED = shared_dir()
SCRIPTS = REPO / "benches" / "eval"


def load(name):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


needs_cli_and_data = pytest.mark.skipif(
    BIN is None or SHARED is None or not (SHARED / "data" / "m2t2-table").is_dir(),
    reason="needs the moma CLI (MOMA_BIN) and the shared data (MOMA_SHARED_DIR)",
)


def run_checks(out_dir, *extra):
    """`issue12_checks.py` on one simulator seed and one sampling seed; its stdout."""
    r = subprocess.run(
        [sys.executable, str(SCRIPTS / "issue12_checks.py"), "--moma", BIN, "--shared",
         str(SHARED), "--sim-seeds", "1", "--seeds", "1", "--out", str(out_dir), *extra],
        capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stderr
    return r.stdout


@needs_cli_and_data
def test_issue12_checks_run_every_check_on_the_cli(tmp_path):
    out = run_checks(tmp_path)
    assert out.startswith("SIMULATED predictions")
    # every set of the local/auto table, with its two verdict columns
    row = next(l for l in out.splitlines() if l.startswith("| gqcnn-primesense | "))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert len(cells) == 9 and cells[8].endswith(("(1/1)", "(0/1)")) and " vs " in cells[8], row
    # m2t2-table (3 frames) and cleargrasp-transparent (2) cannot score K = 3
    assert out.count("too few frames for K = 3") == 6, out
    # re-alignment: 4 sets × 3 methods × 3 brightness rows, and the 9-row summary
    assert sum(" | realign-anchors" in l and l.startswith("| cleargrasp") for l in
               out.splitlines()) == 9, out
    assert "worst frame rise mm" in out and "worse by > 2 mm" in out
    # robust: 4 methods × 3 kinds, and the two counts over 48 rows
    assert "of the plain clean fit: " in out and "/48" in out, out
    # each check kept its moma eval output (the per-frame results) under --out
    for check in ["main", "few-shot", "realign", "robust", "robust-outliers"]:
        assert (tmp_path / check / "sim0" / "results.json").is_file()


@needs_cli_and_data
def test_issue12_checks_pass_eval_args_to_every_run(tmp_path):
    out = run_checks(tmp_path, "--only", "main", "--eval-args", "--edge-margin-px 3")
    assert "moma eval --edge-margin-px 3;" in out.splitlines()[0]
    command = (tmp_path / "main" / "sim0" / "command.txt").read_text()
    assert " --edge-margin-px 3 -o " in command, command


def test_k_standard_error_rule_prefers_the_simpler_model_within_k_se():
    rule = load("auto_rules").one_se
    simple = [1.0, 1.2, 0.8, 1.1, 0.9, 1.0]  # mean 1.0
    # better on average by 0.05, but the paired differences vary: SE of the mean difference
    # = sd([0.1, 0.3, -0.1, 0.2, 0.0, -0.2]) / sqrt(6) ≈ 0.076 > 0.05
    noisy = [0.9, 0.9, 0.9, 0.9, 0.9, 1.2]
    cands = [{"cv_sq": simple}, {"cv_sq": noisy}]
    assert rule(1.0)(cands) == 0
    assert rule(0.5)(cands) == 1  # 0.05 > 0.5 × 0.076
    # a consistent gain (every sample 0.1 lower: SE 0) always wins
    cands = [{"cv_sq": simple}, {"cv_sq": [x - 0.1 for x in simple]}]
    assert rule(1.0)(cands) == 1


@needs_cli_and_data
def test_issue12_checks_on_prediction_folders_match_the_simulator_path(tmp_path):
    """`--pred ROOT` (folders written by `moma simulate --seed 0`) scores exactly what
    `--simulate --sim-seed 0` scores: the same tables, only the header differs."""
    sets = []
    for s in ["gqcnn-primesense", "graspnet6dof-table", "m2t2-table", "cleargrasp-transparent"]:
        sets += ["--set", str(SHARED / "data" / s)]
    subprocess.run([BIN, "simulate", *sets, "--seed", "0", "-o", str(tmp_path / "preds")],
                   check=True, capture_output=True)

    def checks(*extra):
        r = subprocess.run(
            [sys.executable, str(SCRIPTS / "issue12_checks.py"), "--moma", BIN, "--shared",
             str(SHARED), "--seeds", "1", "--only", "main,few-shot", *extra],
            capture_output=True, text=True, timeout=600,
        )
        assert r.returncode == 0, r.stderr
        return r.stdout

    from_sim = checks("--sim-seeds", "1", "--out", str(tmp_path / "sim"))
    from_files = checks("--pred", str(tmp_path / "preds"), "--out", str(tmp_path / "files"))
    assert from_files.splitlines()[0].startswith("SIMULATED predictions (")
    assert "predictions from" in from_files.splitlines()[0]

    def tables(out):
        return [l for l in out.splitlines() if l.startswith("| ")]

    assert len(tables(from_sim)) > 10
    assert tables(from_files) == tables(from_sim)
