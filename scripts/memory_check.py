"""Check the memory estimate of morphmodes_vol.limits against measured peak memory.

Each configuration runs in its own Python process: it builds a generated source/target pair,
notes its resident memory (VmRSS), runs a short registration (few iterations: memory does
not grow with iterations) and reads the peak (VmHWM); the difference is compared with the
estimate. Writes results/memory_check/memory_check.{csv,md}.

    python scripts/memory_check.py            # a few minutes on 2 cores
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import write_csv  # noqa: E402

CONFIGS = [  # (icosphere subdivisions, grid, modes)
    (3, 32, 8),
    (3, 64, 8),
    (3, 96, 8),
    (5, 32, 20),
    (6, 32, 20),
    (6, 48, 40),
]

CHILD = r"""
import json, sys
import numpy as np
import morphmodes_vol as mm
from morphmodes_vol.limits import estimate_memory
from morphmodes_vol.primitives import icosphere

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024

sub, grid, modes = map(int, sys.argv[1:4])
V, F = icosphere(sub)
target = V * [1.1, 0.9, 1.0]
opts = mm.RegistrationOptions(grid=grid, modes=modes, max_iterations=3, max_iterations_per_stage=1)
base = status("VmRSS")
reg = mm.Registration((V, F), (target, F), opts)
reg.run()
peak = status("VmHWM")
est = estimate_memory(len(V), len(F), len(F), modes, reg.quadrature.size, reg.target_grid.size)
print(json.dumps({"vertices": len(V), "grid": grid, "modes": modes,
                  "quadrature_points": reg.quadrature.size, "measured_mb": (peak - base) / 1e6,
                  "estimate_mb": est.total / 1e6}))
"""


def main() -> None:
    out = Path("results/memory_check")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for sub, grid, modes in CONFIGS:
        proc = subprocess.run([sys.executable, "-c", CHILD, str(sub), str(grid), str(modes)],
                              capture_output=True, text=True, check=True)
        row = json.loads(proc.stdout.strip().splitlines()[-1])
        row["ratio"] = row["estimate_mb"] / max(row["measured_mb"], 1e-9)
        rows.append(row)
        print(row, flush=True)
    write_csv(out / "memory_check.csv", rows)
    lines = ["| vertices | grid | modes | quadrature points | measured peak (MB) | estimate (MB) | estimate / measured |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['vertices']} | {r['grid']} | {r['modes']} | {r['quadrature_points']} | "
                     f"{r['measured_mb']:.0f} | {r['estimate_mb']:.0f} | {r['ratio']:.2f} |")
    (out / "memory_check.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
