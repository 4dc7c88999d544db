"""The table of benchmarks/fit_defaults_gpu.sh's results: per `texstream fit` run its wall time, phases and the
materials choice's parts; per dense fit its held-out figures and choice.

    python benchmarks/fit_defaults_summary.py DIR      (DIR: the script's json/ folder)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def materials_line(m: dict | None) -> str:
    if not m:
        return "materials: none"
    cands = ", ".join(f"{c['model']}{' K=' + str(c['k']) if 'k' in c else ''} {c['pooled_psnr_db']:.2f}"
                      + (f" ({c['seconds']['fit']:.2f}+{c['seconds']['score']:.2f} s, {c.get('iterations')} it)"
                         if "seconds" in c else "") for c in m.get("candidates", []))
    parts = m.get("seconds_by_part")
    return (f"materials: chose {m.get('chosen')} K={m.get('k')} in {m.get('seconds', 0):.2f} s"
            + (f" (parts {json.dumps({k: round(v, 3) for k, v in parts.items()})})" if parts else "")
            + (f", chosen fit {m['chosen_fit_seconds']:.2f} s" if "chosen_fit_seconds" in m else "")
            + f"; validation: {cands}")


def stages_line(trace: Path) -> str:
    """Trace rows per stage of a fit (the fit of every photo: "fit"; then "materials", "traced polish")."""
    if not trace.is_file():
        return "trace: none"
    rows: dict = {}
    for r in json.loads(trace.read_text()):
        rows[r.get("stage", "fit")] = rows.get(r.get("stage", "fit"), 0) + 1
    return "trace rows " + json.dumps(rows)


def main() -> None:
    d = Path(sys.argv[1])
    for p in sorted(d.glob("*.json")):
        if p.name.endswith((".model.json", ".eval.json", ".trace.json")):
            continue
        doc = json.loads(p.read_text())
        for r in doc["runs"]:
            print(f"{p.stem}: wall {r['wall_s']:.2f} s, exit {r['exit_code']}, timings "
                  f"{json.dumps({k: round(v, 2) for k, v in (r.get('timings_s') or {}).items()})}, "
                  f"iterations {r.get('iterations')}")
        man = d / f"{p.stem}.model.json"
        if man.is_file():
            print("   ", materials_line(json.loads(man.read_text()).get("materials")))
        print("   ", stages_line(d / f"{p.stem}.trace.json"))
    for p in sorted(d.glob("*.eval.json")):
        e = json.loads(p.read_text())
        m = json.loads((d / p.name.replace(".eval.json", ".model.json")).read_text())
        print(f"{p.name}: held out pooled {e.get('pooled_psnr_db')}, worst {e.get('worst_psnr_db')} "
              f"({e.get('worst_view')}); {materials_line(m.get('materials'))}; trace rows {m['final']['iteration']}; "
              f"{stages_line(d / p.name.replace('.eval.json', '.trace.json'))}")


if __name__ == "__main__":
    main()
