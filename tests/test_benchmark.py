"""lerobot-iupe-benchmark --quick end to end (real datasets, lerobot-train, LeRobot's evaluation code)."""

import dataclasses
import json
import warnings
from pathlib import Path

import matplotlib.image
from conftest import CHECKPOINT, run_cli, run_in_process, run_script

from lerobot_iupe.benchmark import CONTINUOUS, PRESETS, Benchmark, Run, method_flags, read_training_run
from lerobot_iupe.benchmark.presets import METAWORLD
from lerobot_iupe.benchmark.report import _cell, metaworld_section, plot_results

LAYOUTS = ("demo", "heldout")


def test_quick_benchmark_writes_records_tables_and_plots(tmp_path):
    """On a maze, which has both layout sets (an env without layouts is scored by the same code, with one set:
    test_references_are_read_from_the_recorded_agent_rows_instead_of_played_again)."""
    out = tmp_path / "out"
    args = ["--quick", "--envs", "maze3", "--methods", "expert", "random", "bco", "iupe"]
    # two runs at a time: each run is recorded once, with its own evaluation
    run_cli("lerobot-iupe-benchmark", *args, "--jobs=2", f"--work={tmp_path / 'work'}", f"--out={out}")
    records = json.loads((out / "results.json").read_text())
    keys = {"env", "method", "seed", "eval_layouts", "P", "AER", "success_rate", "train_seconds"}
    assert all(keys <= set(r) for r in records)
    trained = [r for r in records if r["method"] in ("bco", "iupe")]
    assert len(trained) == 8
    # every checkpoint under both evaluation rules, on both layout sets
    assert {(r["env"], r["method"], r["eval_layouts"], r["eval_mode"]) for r in trained} == {
        ("maze3", m, lay, mode) for m in ("bco", "iupe") for lay in LAYOUTS for mode in ("argmax", "sample")
    }
    # references are the built-in agents' returns on exactly the scored episodes: Random scores 0, Expert 1
    for layouts in LAYOUTS:
        rows = [r for r in records if r["eval_layouts"] == layouts]
        (expert,) = [r for r in rows if r["method"] == "expert"]
        (random,) = [r for r in rows if r["method"] == "random"]
        assert {(r["R_expert"], r["R_random"]) for r in rows} == {(expert["AER"], random["AER"])}
        assert random["P"] == 0.0 and expert["P"] == 1.0
    demo_random, heldout_random = ({r["R_random"] for r in records if r["eval_layouts"] == lay} for lay in LAYOUTS)
    assert demo_random != heldout_random
    # each row says how its checkpoint was selected; maze rollouts select on the demonstration layouts
    # (BCO(α) on its rollouts, which play the mode; IUPE, whose rollouts draw, on 4 episodes of its own by the mode)
    rule = "best rollout success of a cycle (the env's success, then the goal reached at any step, 2 cycles × 4 "
    assert all(r["selection"].startswith(rule) for r in trained if r["method"] == "bco")
    own = "best success of a cycle on 4 episodes of its own played by the mode (as lerobot-eval plays), the same "
    assert all(r["selection"].startswith(own) for r in trained if r["method"] == "iupe")
    assert {"demonstration" in r["selection"] for r in trained} == {True}
    assert all(r["train_seconds"] > 0 and r["cycles"] for r in trained)
    assert all(r["timing"]["idm_s"] > 0 and r["timing"]["rollouts_s"] > 0 for r in trained)
    assert {r["method"]: r["timing"]["selection_s"] > 0 for r in trained} == {"bco": False, "iupe": True}
    report = (out / "results.md").read_text()
    assert "IUPE (paper)" in report and "held-out layouts" in report and "Where the time goes" in report
    for plot in ("cycles.png", "performance.png"):  # real figures: decodable PNGs with something drawn on them
        pixels = matplotlib.image.imread(out / plot)
        assert pixels.ndim == 3 and min(pixels.shape[:2]) >= 200 and pixels[..., :3].std() > 0.02
    # the later calls train nothing, so they run in this process (the first one ran as the installed command)
    # a second call resumes: every run is already recorded, nothing is trained again
    again = run_in_process("lerobot-iupe-benchmark", *args, f"--work={tmp_path / 'work'}", f"--out={out}")
    assert again.returncode == 0 and "lerobot-train" not in again.stdout, again.stderr[-3000:]
    assert (out / "results.md").read_text().count("- `lerobot-iupe-benchmark --quick") == 2  # both calls listed
    # a fresh work folder seeded from the report (a fresh clone): nothing is trained, every record is kept
    published = json.loads((out / "results.json").read_text())
    fresh_work = f"--work={tmp_path / 'fresh'}"
    fresh = run_in_process("lerobot-iupe-benchmark", *args, fresh_work, f"--out={out}", f"--from={out}")
    assert fresh.returncode == 0 and "lerobot-train" not in fresh.stdout
    assert f"{len(published)} records added" in fresh.stdout
    assert json.loads((out / "results.json").read_text()) == published
    assert len(json.loads((out / "calls.json").read_text())) == 3
    # a report scored against other references is scored again against the scored episodes' own
    stale = tmp_path / "stale"
    stale.mkdir()
    old = [dict(r, R_random=r["R_random"] - 7.0, P=0.5) if r["eval_layouts"] == "demo" else r for r in published]
    (stale / "results.json").write_text(json.dumps(old))
    rescored = run_in_process(
        "lerobot-iupe-benchmark", *args, f"--work={tmp_path / 'rescored'}", f"--out={stale}", f"--from={stale}"
    )
    assert rescored.returncode == 0 and "lerobot-train" not in rescored.stdout
    assert json.loads((stale / "results.json").read_text()) == published
    # a report that still holds a row of an older configuration of a recorded run: the run's own row stays alone
    older = tmp_path / "older"
    older.mkdir()
    (row,) = [r for r in published if (r["method"], r["eval_layouts"], r["eval_mode"]) == ("iupe", "demo", "argmax")]
    (older / "results.json").write_text(json.dumps([*published, dict(row, config="0ld0ld0ld0", P=-9.0)]))
    work = f"--work={tmp_path / 'work'}"
    merged = run_in_process("lerobot-iupe-benchmark", *args, work, f"--out={older}", f"--from={older}")
    assert merged.returncode == 0 and "lerobot-train" not in merged.stdout and "1 records added" in merged.stdout
    assert json.loads((older / "results.json").read_text()) == published


def test_references_are_read_from_the_recorded_agent_rows_instead_of_played_again(tmp_path):
    """A resumed call (or one seeded by --from) takes R_expert and R_random from the built-in agents' recorded rows
    of the same configuration; a row of another configuration does not stand for these episodes."""
    preset, episodes = PRESETS["cartpole"], 5
    bench = Benchmark(tmp_path, eval_episodes=episodes)
    for agent, aer in (("expert", 123.0), ("random", 4.5)):
        config = Run("table1", "cartpole", preset, agent, None, {}, {}).config_key(episodes)
        bench._save({"table": "table1", "env": "cartpole", "method": agent, "seed": None, "config": config,
                     "eval_layouts": None, "eval_mode": None, "AER": aer, "success_rate": 0.0})  # fmt: skip
    assert bench.references(preset) == {None: (123.0, 4.5)}  # played, CartPole's expert would score 500
    other = Benchmark(tmp_path, eval_episodes=3)  # the same rows, but 3 scored episodes: played for real
    assert other.references(preset)[None][0] == 500.0


def test_jobs_below_one_is_refused_and_nothing_is_written(tmp_path):
    work, out = tmp_path / "work", tmp_path / "out"
    result = run_in_process("lerobot-iupe-benchmark", "--quick", "--jobs=0", f"--work={work}", f"--out={out}")
    assert result.returncode == 2
    assert "--jobs: must be 1 or more" in result.stderr
    assert not work.exists() and not out.exists()


def test_from_a_folder_without_results_is_refused_and_nothing_is_written(tmp_path):
    work, out = tmp_path / "work", tmp_path / "out"
    args = ["--quick", f"--from={tmp_path}", f"--work={work}", f"--out={out}"]
    result = run_in_process("lerobot-iupe-benchmark", *args)
    assert result.returncode == 2 and "--from" in result.stderr and "results.json" in result.stderr
    assert not work.exists() and not out.exists()


def test_method_flags_name_the_mechanisms():
    assert method_flags("bco") == ["--policy.sampling=false", "--policy.exploration=false", "--policy.attention=false"]
    assert method_flags("SE") == ["--policy.sampling=true", "--policy.exploration=true", "--policy.attention=false"]
    assert method_flags("iupe") == [] and method_flags("bc") == ["--policy.supervised=true"]


def test_records_are_keyed_by_everything_that_determines_them():
    preset = PRESETS["cartpole"]
    assert preset.data_key(quick=True) != preset.data_key(quick=False)  # --quick never reuses full datasets
    play = dataclasses.replace(preset, data=dataclasses.replace(preset.data, pre_demos_agent="play"))
    assert play.data_key(quick=False) != preset.data_key(quick=False)  # play pre-demonstrations are other data
    assert preset.data_key(quick=False) == "2b950ece34"  # the committed rows' key: unchanged by the field
    run = Run("table1", "cartpole", preset, "iupe", 0, {}, {})
    changed = dataclasses.replace(preset, train=dataclasses.replace(preset.train, policy={"idm_lr": "1e-2"}))
    assert run.config_key(100) != dataclasses.replace(run, preset=changed).config_key(100)
    assert run.config_key(100) != run.config_key(50)
    # rows selected on the exploring rollouts (before selection episodes existed) are not taken for today's IUPE
    paper = dataclasses.replace(preset, train=dataclasses.replace(preset.train, policy={"selection_episodes": "0"}))
    assert run.plays_selection_episodes and not dataclasses.replace(run, preset=paper).plays_selection_episodes
    assert not dataclasses.replace(run, method="bco").plays_selection_episodes  # its rollouts play the mode
    twenty = dataclasses.replace(preset, train=dataclasses.replace(preset.train, policy={"selection_episodes": "20"}))
    assert Run("table1", "cartpole", twenty, "bco", 0, {}, {}).plays_selection_episodes  # told to: its own
    # BC keeps its last step (the committed rows) unless the preset gives selection episodes: then other rows
    assert not dataclasses.replace(run, method="bc").plays_selection_episodes
    bc_twenty = Run("table1", "cartpole", twenty, "bc", 0, {}, {})
    assert bc_twenty.plays_selection_episodes
    assert bc_twenty.config_key(100) != dataclasses.replace(bc_twenty, preset=preset).config_key(100)
    assert run.config_key(100) != dataclasses.replace(run, preset=paper).config_key(100)
    assert run.config_key(100) == Run("table1", "cartpole", preset, "iupe", 0, {}, {}).config_key(100)
    # SO-101 from uniformly random pre-demonstrations: the play column's budget, other data, and only the learners
    # that read pre-demonstrations; it keeps the observation and heads its rows were measured with
    uniform, play = CONTINUOUS["so101_uniform"], CONTINUOUS["so101_pickplace"]
    assert play.env == {**uniform.env, "relative_positions": True} and uniform.data.pre_demos_agent == "random"
    binary_grasp = {**uniform.train.policy, "binary_action_dims": "[3]"}
    assert play.train == dataclasses.replace(
        uniform.train, policy=binary_grasp, sampling_policy={"max_success_share": "0.8"}
    )
    # the sampling rule's settings reach the learners that sample, and only them (BC's and BCO(α)'s rows stay)
    flags = {m: Run("continuous", "so101_pickplace", play, m, 0, {}, {}).train_flags for m in ("bc", "bco", "iupe")}
    assert "--policy.max_success_share=0.8" in flags["iupe"]
    assert not any("max_success_share" in f for f in flags["bc"] + flags["bco"])
    assert "--env.relative_positions=true" in play.env_flags()
    assert uniform.data_key(quick=False) != play.data_key(quick=False)
    everything = ["expert", "random", "bc", "bco", "iupe"]
    assert uniform.compared(everything) == ["bco", "iupe"] and play.compared(everything) == everything
    # Meta-World's IDM window and keys reach the learners that label with an IDM, and BC's rows stay
    push = METAWORLD["mw-push"]
    flags = {m: Run("metaworld", "mw-push", push, m, 0, {}, {}).train_flags for m in ("bc", "bco", "iupe")}
    for method in ("bco", "iupe"):
        assert {"--policy.idm_context=3", "--policy.idm_observation_keys=[observation.state]"} <= set(flags[method])
    assert not any("idm_" in f for f in flags["bc"]) and "--policy.selection_episodes=10" in flags["bc"]


def test_a_play_setting_changes_the_rows_of_the_learners_that_read_pre_demonstrations_only():
    """Meta-World's play holds commands (--env.play_held_moves, pre-demonstrations only): the learners that read
    the pre-demonstrations get new datasets and rows; BC, ILPO and the built-in agents keep theirs."""
    push = METAWORLD["mw-push"]
    before = dataclasses.replace(push, data=dataclasses.replace(push.data, pre_demos_env={}))
    assert push.data_key(quick=False) == before.data_key(quick=False) == "ff3c9e4b2b"  # the committed rows' key
    assert push.pre_demos_key(quick=False) != push.data_key(quick=False)
    assert before.pre_demos_key(quick=False) == before.data_key(quick=False)
    assert "--env.play_held_moves=0.5" in push.pre_demos_flags() and not any("play" in f for f in push.env_flags())
    for method in ("expert", "random", "bc", "ilpo", "bco", "iupe"):
        run = Run("metaworld", "mw-push", push, method, None if method in ("expert", "random") else 0, {}, {})
        unchanged = run.config_key(50) == dataclasses.replace(run, preset=before).config_key(50)
        assert unchanged == (method in ("expert", "random", "bc", "ilpo")), method


def test_cycles_are_read_from_the_checkpoint_records(cartpole_run):
    checkpoint = cartpole_run / CHECKPOINT
    log = "INFO step:25 smpl:3K ep:5 epch:0.1 loss:0.6 grdn:1 lr:1e-03 updt_s:0.010 data_s:0.100\n"
    cycles, timing = read_training_run(checkpoint, log, steps=200)
    assert [c["cycle"] for c in cycles] == [1, 2, 3, 4] and [c["step"] for c in cycles] == [50, 100, 150, 200]
    assert timing == {
        "rollouts_s": cycles[-1]["rollouts_s"], "idm_s": cycles[-1]["idm_s"],
        "selection_s": cycles[-1]["selection_s"], "data_loading_s": 20.0,
    }  # fmt: skip


def test_cells_give_the_sample_standard_deviation_over_seeds():
    rows = [{"P": p, "AER": 10 * p} for p in (0.0, 1.0, 2.0)]
    assert _cell(rows) == "1.000 ± 1.000 / 10.000 ± 10.000 (n=3)"  # ddof = 1 (ddof = 0 would give 0.816)


def test_the_metaworld_table_gives_success_per_task_over_seeds_with_the_other_papers_rows_apart():
    def row(env, method, seed, rate):
        return {"table": "metaworld", "env": env, "method": method, "seed": seed, "eval_mode": "argmax",
                "success_rate": rate}  # fmt: skip

    records = [row("mw-push", "iupe", s, r) for s, r in enumerate((0.5, 0.7, 0.6))]
    records += [row("mw-reach", "iupe", 0, 1.0), row("mw-push", "bc", 0, 0.9), row("mw-reach", "bc", 0, 0.8)]
    records += [{**row("mw-push", "expert", None, 1.0), "eval_mode": None}]
    lines = metaworld_section(records, ["expert", "bc", "bco", "iupe"])
    table = [line for line in lines if line.startswith("| ")]
    assert table[0] == "| method | reach | push | mean |"  # MT10's order, only the tasks run
    assert "| IUPE (ours) | 100 | 60 ± 10 (n=3) | 80.0 |" in table  # a task's mean first, then over tasks
    assert "| BC (ours) | 80 | 90 | 85.0 |" in table
    assert "| Expert (ours) | – | 100 | – |" in table  # no mean over a task it has no row for
    assert not any(line.startswith("| BCO(α)") for line in table)  # a method never run has no row
    assert "| DP3 (other paper's protocol) | 24 | 51 | 37.5 |" in table
    with warnings.catch_warnings():  # no section, and no numpy warning from a mean over no task
        warnings.simplefilter("error")
        assert metaworld_section([r for r in records if r["table"] != "metaworld"], ["iupe"]) == []


def test_run_labels_script_names_a_missing_runs_folder_and_writes_nothing(tmp_path):
    """benchmarks/measure/run_labels.py: a --runs folder the --work folder lacks is named, not a traceback."""
    script = Path(__file__).parent.parent / "benchmarks" / "measure" / "run_labels.py"
    out = tmp_path / "out"
    args = [f"--work={tmp_path}", "--runs", "table1/maze10", f"--out={out}"]
    result = run_script(script, *args)
    assert result.returncode == 2
    assert f"--runs table1/maze10: no folder {tmp_path / 'runs' / 'table1' / 'maze10'}" in result.stderr
    assert not out.exists()


def test_goal_script_names_a_checkpoint_folder_without_config(tmp_path):
    """benchmarks/measure/goal.py: a --checkpoint that is not a pretrained_model folder is named, not a traceback."""
    script = Path(__file__).parent.parent / "benchmarks" / "measure" / "goal.py"
    result = run_script(script, f"--checkpoint={tmp_path}")
    assert result.returncode == 2
    assert f"--checkpoint={tmp_path} holds no config.json" in result.stderr


def test_mode_script_names_a_non_dataset_and_a_checkpoint_without_its_training_state(tmp_path):
    """benchmarks/measure/mode.py: a --data folder without meta/info.json, and --weights=latest on a folder without
    the training state, are named, not a traceback."""
    script = Path(__file__).parent.parent / "benchmarks" / "measure" / "mode.py"
    args = [f"--data={tmp_path}", "--checkpoints", str(tmp_path)]
    result = run_script(script, *args)
    assert result.returncode == 2
    assert f"--data={tmp_path} is not a LeRobot dataset (no meta/info.json)" in result.stderr
    # the run's last weights need the training state lerobot-train saves beside a checkpoint
    (tmp_path / "meta").mkdir()
    (tmp_path / "meta" / "info.json").write_text("{}")
    latest = run_script(script, *args, "--weights", "latest")
    assert latest.returncode == 2
    assert f"--weights=latest: {tmp_path} holds no iupe_training_state.pt" in latest.stderr


def test_the_cycle_plot_draws_rollout_curves_and_skips_a_selecting_bc_run(tmp_path):
    """A BC run that selects records cycles without rollouts; the plot must not read rollout rates from them."""
    selecting = {"cycle": 1, "step": 200, "selection_episodes": 10, "selection_env_success_rate": 0.5}
    rollouts = {"cycle": 1, "step": 200, "success_rate": 0.5, "return": 10.0}
    rows = [
        {"table": "continuous", "env": "lunarlander", "method": method, "seed": 0, "eval_layouts": None,
         "eval_mode": "argmax", "P": 0.9, "cycles": [cycle, {**cycle, "cycle": 2}]}
        for method, cycle in (("bc", selecting), ("iupe", rollouts))
    ]  # fmt: skip
    assert plot_results(rows, tmp_path) == [tmp_path / "cycles.png"]
    assert matplotlib.image.imread(tmp_path / "cycles.png").shape[0] > 0
