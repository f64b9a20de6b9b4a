"""How right the labels were that each benchmark run's policy learned from: the selected checkpoint's IDM relabels
the run's own expert dataset (by `lerobot-iupe-relabel`, argmax) and is compared with the true actions the
benchmark kept beside it (`<data>-actions`), on every frame with a successor. Discrete actions only.

    python scripts/measure_run_labels.py --work outputs/bench-r3 --runs table1/maze10 ablation/maze10
Writes <out>/run_labels.json and prints a table per method (mean ± std over seeds, ddof = 1).
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

BIN = Path(sys.executable).parent


def actions_with_successor(repo_id: str, root: Path) -> np.ndarray:
    table = LeRobotDataset(repo_id, root=root, video_backend="pyav").hf_dataset.with_format("numpy")
    episodes = np.asarray(table["episode_index"])
    return np.asarray(table["action"]).reshape(-1)[np.append(episodes[:-1] == episodes[1:], False)]


def label_accuracy(run: Path) -> dict:
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
        "label_accuracy": float((labels == truth).mean()),
        "frames": int(len(truth)),
        "selected_cycle": selected,
        "rollout_success_at_selection": next((c["success_rate"] for c in cycles if c["cycle"] == selected), None),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="outputs/bench-r3", help="a benchmark's --work folder")
    parser.add_argument("--runs", nargs="+", default=["table1/maze10", "ablation/maze10"], help="<table>/<env>")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    runs = sorted(
        run
        for folder in args.runs
        for run in (Path(args.work) / "runs" / folder).iterdir()
        if (run / CHECKPOINT / "model.safetensors").exists()
    )
    rows = []
    for run in runs:
        rows.append(label_accuracy(run))
        print(json.dumps(rows[-1]), flush=True)
    command = " ".join(["python", "scripts/measure_run_labels.py", *sys.argv[1:]])
    Path(args.out, "run_labels.json").write_text(json.dumps({"commands": [command], "rows": rows}, indent=1) + "\n")
    by_method: dict[str, list[float]] = {}
    for row in rows:
        by_method.setdefault(re.sub(r"-s\d+$", "", row["run"]), []).append(row["label_accuracy"])
    print("| runs | label accuracy per seed | mean ± std |\n|---|---|---|")
    for method, values in by_method.items():
        spread = np.std(values, ddof=1) if len(values) > 1 else 0.0
        print(f"| {method} | {', '.join(f'{v:.3f}' for v in values)} | {np.mean(values):.3f} ± {spread:.3f} |")


if __name__ == "__main__":
    main()
