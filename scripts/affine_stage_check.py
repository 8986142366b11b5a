"""Ground-truth error of the affine stage alone, run to convergence (1 mode, stall 1e-5,
300 iterations), for lion poses given on the command line:

    python scripts/affine_stage_check.py 01 04 05 07
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import data_dir  # noqa: E402

import morphmodes_vol as mm  # noqa: E402

data = data_dir()
if data is None:
    sys.exit("shared data not found (set MORPHMODES_DATA)")
d = str(data / "lion-poses") + "/"
for pose in sys.argv[1:]:
    target = d + f"lion-{pose}.obj"
    r = mm.register(
        d + "lion-reference.obj", target, ground_truth=target,
        modes=1, max_iterations_per_stage=300, stall_start=1e-5, stall_end=1e-5,
    )
    m = r.metrics
    print(
        f"{pose} identity {m['identity_error']:.4f} affine-only {m['ground_truth_error']:.4f} "
        f"sdf rms {m['initial_sdf_rms']:.4f} -> {m['final_sdf_rms']:.4f} {r.evaluations}",
        flush=True,
    )
