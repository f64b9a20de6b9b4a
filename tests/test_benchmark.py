"""lerobot-iupe-benchmark --quick end to end (real datasets, lerobot-train, LeRobot's evaluation code)."""

import json

from conftest import run_cli

from lerobot_iupe.benchmark import method_flags, parse_training_log


def test_quick_benchmark_writes_records_tables_and_plots(tmp_path):
    out = tmp_path / "out"
    args = ["--quick", "--envs", "cartpole", "maze3", "--methods", "random", "bco", "iupe"]
    # two runs at a time: each run is recorded once, with its own evaluation
    run_cli("lerobot-iupe-benchmark", *args, "--jobs=2", f"--work={tmp_path / 'work'}", f"--out={out}")
    records = json.loads((out / "results.json").read_text())
    keys = {"env", "method", "seed", "eval_layouts", "P", "AER", "success_rate", "train_seconds"}
    assert all(keys <= set(r) for r in records)
    trained = [r for r in records if r["method"] in ("bco", "iupe")]
    assert len(trained) == 6
    assert {(r["env"], r["method"], r["eval_layouts"]) for r in trained} == {
        ("cartpole", "bco", None),
        ("cartpole", "iupe", None),
        ("maze3", "bco", "demo"),
        ("maze3", "bco", "heldout"),
        ("maze3", "iupe", "demo"),
        ("maze3", "iupe", "heldout"),
    }
    assert all(r["train_seconds"] > 0 and r["cycles"] for r in trained)
    assert all(r["timing"]["idm_s"] > 0 and r["timing"]["rollouts_s"] > 0 for r in trained)
    report = (out / "results.md").read_text()
    assert "IUPE (paper)" in report and "held-out layouts" in report and "Where the time goes" in report
    assert (out / "cycles.png").stat().st_size > 0 and (out / "performance.png").stat().st_size > 0
    # a second call resumes: every run is already recorded, nothing is trained again
    again = run_cli("lerobot-iupe-benchmark", *args, f"--work={tmp_path / 'work'}", f"--out={out}")
    assert "lerobot-train" not in again.stdout
    assert (out / "results.md").read_text().count("- `lerobot-iupe-benchmark --quick") == 2  # both calls listed


def test_jobs_below_one_is_refused_and_nothing_is_written(tmp_path):
    work, out = tmp_path / "work", tmp_path / "out"
    result = run_cli("lerobot-iupe-benchmark", "--quick", "--jobs=0", f"--work={work}", f"--out={out}", check=False)
    assert result.returncode == 2
    assert "--jobs: must be 1 or more" in result.stderr
    assert not work.exists() and not out.exists()


def test_method_flags_name_the_mechanisms():
    assert method_flags("bco") == ["--policy.sampling=false", "--policy.exploration=false", "--policy.attention=false"]
    assert method_flags("SE") == ["--policy.sampling=true", "--policy.exploration=true", "--policy.attention=false"]
    assert method_flags("iupe") == [] and method_flags("bc") == ["--policy.supervised=true"]


def test_training_log_parsing():
    log = (
        "INFO IUPE cycle 1: success r=0.25 return=-310.5 IDM acc=0.9 ... time so far: rollouts 1.50s IDM 2.25s\n"
        "INFO step:25 smpl:3K ep:5 epch:0.1 loss:0.6 grdn:1 lr:1e-03 updt_s:0.010 data_s:0.100\n"
        "INFO IUPE cycle 2: success r=1.00 return=-90.0 IDM acc=0.9 ... time so far: rollouts 3.00s IDM 4.50s\n"
    )
    cycles, timing = parse_training_log(log, steps=50)
    assert cycles == [
        {"cycle": 1, "success_rate": 0.25, "return": -310.5},
        {"cycle": 2, "success_rate": 1.0, "return": -90.0},
    ]
    assert timing == {"rollouts_s": 3.0, "idm_s": 4.5, "data_loading_s": 5.0}
