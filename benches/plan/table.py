"""The planning tasks' table from their plan.json files:
    python3 benches/plan/table.py OUT_DIR/tasks"""
import json
import pathlib
import sys

root = pathlib.Path(sys.argv[1])
print("| task | start mm | fitted: planned | fitted: executed (truth) | untrained: executed (truth) | rollouts | s |")
print("|---|---|---|---|---|---|---|")
for task in sorted(p for p in root.iterdir() if p.is_dir()):
    runs = {}
    for model in ("fitted", "untrained"):
        path = task / model / "plan.json"
        runs[model] = json.loads(path.read_text()) if path.is_file() else None
    f, u = runs["fitted"], runs["untrained"]
    mm = lambda r, k: f"{1e3 * r[k]['final_chamfer_m']:.1f}" if r else "–"
    print(f"| {task.name} | {mm(f, 'start')} | {mm(f, 'planned')} | {mm(f, 'executed')} | {mm(u, 'executed')} "
          f"| {f['rollouts'] if f else '–'} | {f['seconds']:.0f} |" if f else f"| {task.name} | failed |")
