"""Gradient refinement alone against MPPI alone, per planning task: MPPI's
best cost after its 10 iterations (201 rollouts) from the fitted run's
first search, and the first gradient step whose cost is at least as low.
    python3 benches/plan/compare.py OUT_DIR/tasks"""
import json
import pathlib
import sys

root = pathlib.Path(sys.argv[1])
print("| task | MPPI cost, 201 rollouts | gradient cost, 67 rollouts | rollouts for the gradient to reach MPPI's | met |")
print("|---|---|---|---|---|")
met = 0
total = 0
for task in sorted(p for p in root.iterdir() if p.is_dir()):
    fitted, gradient = task / "fitted" / "plan.json", task / "gradient" / "plan.json"
    if not (fitted.is_file() and gradient.is_file()):
        continue
    mppi = json.loads(fitted.read_text())["history"]["mppi"][9]
    steps = json.loads(gradient.read_text())["history"]["gradient"]
    reach = next((k + 1 for k, c in enumerate(steps) if c <= mppi), None)
    ok = min(steps) <= mppi and (reach is not None and reach <= 67)
    met += ok
    total += 1
    print(f"| {task.name} | {mppi:.3e} | {min(steps):.3e} | {reach if reach else '–'} | {'yes' if ok else 'no'} |")
print(f"\nmet on {met} of {total}")
