"""How right the labels were that each benchmark run's policy learned from: the selected checkpoint's IDM relabels
the run's own expert dataset (by `lerobot-iupe-relabel`, argmax) and is compared with the true actions the
benchmark kept beside it (`<data>-actions`), on every frame with a successor: accuracy for discrete actions, R²
per dimension (and their mean) for continuous ones.

    python benchmarks/measure/run_labels.py --work outputs/bench-r3 --runs table1/maze10 ablation/maze10
Adds its rows to <out>/run_labels.json (replacing those of the same runs) and prints a table per method (mean ±
std over seeds, ddof = 1). BC runs (trained on the true actions, no IDM) are skipped.
"""

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.benchmark import CHECKPOINT
from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.policy.algorithm import r_squared

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line  # noqa: E402

BIN = Path(sys.executable).parent


def actions_with_successor(repo_id: str, root: Path) -> np.ndarray:
    """The ``action`` column (N', D) on the frames that have a successor in their episode."""
    dataset = LeRobotDataset(repo_id, root=root, video_backend="pyav")
    episodes = column_array(dataset.hf_dataset, "episode_index")
    actions = action_array(dataset).reshape(len(episodes), -1)
    return actions[np.append(episodes[:-1] == episodes[1:], False)]


def trained_on_true_actions(run: Path) -> bool:
    """BC runs: their IDM was never trained, so there is nothing to measure."""
    return json.loads((run / CHECKPOINT / "config.json").read_text()).get("supervised", False)


def label_score(labels: np.ndarray, truth: np.ndarray) -> dict:
    if np.issubdtype(truth.dtype, np.integer):
        return {"label_accuracy": float((labels == truth).all(axis=1).mean())}
    per_dimension = [r_squared(labels[:, d], truth[:, d]) for d in range(truth.shape[1])]
    return {"label_r2": float(np.mean(per_dimension)), "label_r2_per_dimension": per_dimension}


def score_run(run: Path) -> dict:
    checkpoint = run / CHECKPOINT
    dataset = json.loads((checkpoint / "train_config.json").read_text())["dataset"]
    root = Path(dataset["root"])
    truth = actions_with_successor(dataset["repo_id"] + "-actions", root.with_name(root.name + "-actions"))
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / root.name
        shutil.copytree(root, copy)
        relabel = [str(BIN / "lerobot-iupe-relabel"), f"--policy.path={checkpoint}", "--dataset.video_backend=pyav"]
        relabel += [f"--dataset.repo_id={dataset['repo_id']}", f"--dataset.root={copy}"]
        subprocess.run(relabel, check=True, capture_output=True, text=True)
        labels = actions_with_successor(dataset["repo_id"], copy)
    log = checkpoint / "iupe_cycles.jsonl"  # absent when training stopped before the first cycle ended
    cycles = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    selected = max((c["cycle"] for c in cycles if c["selected"]), default=None)
    return {
        "run": f"{run.parent.parent.name}/{run.parent.name}/{run.name}",
        **label_score(labels, truth),
        "frames": int(len(truth)),
        "selected_cycle": selected,
        "rollout_success_at_selection": next((c["success_rate"] for c in cycles if c["cycle"] == selected), None),
    }


def save(path: Path, command: str, rows: list[dict]) -> None:
    """Add ``rows`` to the file's, replacing rows of the same runs, and ``command`` to its commands."""
    saved = json.loads(path.read_text()) if path.exists() else {"commands": [], "rows": []}
    runs = {row["run"] for row in rows}
    saved["rows"] = [row for row in saved["rows"] if row["run"] not in runs] + rows
    saved["commands"] = [c for c in saved["commands"] if c != command] + [command]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(saved, indent=1) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="outputs/bench-r3", help="a benchmark's --work folder")
    parser.add_argument("--runs", nargs="+", default=["table1/maze10", "ablation/maze10"], help="<table>/<env>")
    parser.add_argument("--out", default="benchmarks", help="where run_labels.json goes")
    args = parser.parse_args()
    for folder in args.runs:
        if not (Path(args.work) / "runs" / folder).is_dir():
            parser.error(f"--runs {folder}: no folder {Path(args.work) / 'runs' / folder} (<table>/<env> of --work)")
    runs = sorted(
        run
        for folder in args.runs
        for run in (Path(args.work) / "runs" / folder).iterdir()
        if (run / CHECKPOINT / "model.safetensors").exists() and not trained_on_true_actions(run)
    )
    rows = []
    for run in runs:
        rows.append(score_run(run))
        print(json.dumps(rows[-1]), flush=True)
    command = command_line()
    save(Path(args.out) / "run_labels.json", command, rows)
    by_method: dict[str, list[float]] = {}
    for row in rows:
        score = row.get("label_accuracy", row.get("label_r2"))
        by_method.setdefault(re.sub(r"-s\d+$", "", row["run"]), []).append(score)
    print("| runs | label accuracy (discrete) or mean R² (continuous) per seed | mean ± std |\n|---|---|---|")
    for method, values in by_method.items():
        spread = np.std(values, ddof=1) if len(values) > 1 else 0.0
        print(f"| {method} | {', '.join(f'{v:.3f}' for v in values)} | {np.mean(values):.3f} ± {spread:.3f} |")


if __name__ == "__main__":
    main()
