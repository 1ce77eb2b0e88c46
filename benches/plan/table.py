"""The planning tasks' table from their plan.json files (millimetres):
    python3 benches/plan/table.py OUT_DIR/tasks"""
import json
import pathlib
import sys

root = pathlib.Path(sys.argv[1])


def mm(value):
    return "–" if value is None else f"{1e3 * value:.1f}"


print("| task | start: Chamfer / symmetric / Track | fitted, planned: symmetric / Track | fitted, executed: Chamfer / symmetric / Track | untrained, executed: symmetric / Track | rollouts | s |")
print("|---|---|---|---|---|---|---|")
for task in sorted(p for p in root.iterdir() if p.is_dir()):
    runs = {}
    for model in ("fitted", "untrained"):
        path = task / model / "plan.json"
        runs[model] = json.loads(path.read_text()) if path.is_file() else None
    f, u = runs["fitted"], runs["untrained"]
    if f is None:
        print(f"| {task.name} | (no plan.json) |")
        continue
    s, p, e = f["start"], f["planned"], f["executed"]
    ue = u["executed"] if u else {"final_symmetric_chamfer_m": None, "final_track_m": None}
    print(
        f"| {task.name} | {mm(s['final_chamfer_m'])} / {mm(s['final_symmetric_chamfer_m'])} / {mm(s['final_track_m'])} "
        f"| {mm(p['final_symmetric_chamfer_m'])} / {mm(p['final_track_m'])} "
        f"| {mm(e['final_chamfer_m'])} / {mm(e['final_symmetric_chamfer_m'])} / {mm(e['final_track_m'])} "
        f"| {mm(ue['final_symmetric_chamfer_m'])} / {mm(ue['final_track_m'])} | {f['rollouts']} | {f['seconds']:.0f} |"
    )
