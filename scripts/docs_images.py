"""Copy the experiment plots from results/ into docs/img/ as small palette PNGs.

    python scripts/docs_images.py            # after running the exp*.py scripts

Each PNG is quantized to 96 colors (Pillow, a matplotlib dependency) so the pictures in
git stay at a few hundred KB in total.
"""

from __future__ import annotations

import sys
from pathlib import Path

from _data import ROOT

IMAGES = [
    "exp1_rotation/exp1_error_vs_angle.png",
    "exp1_rotation/exp1_renders.png",
    "exp2_adaptive/exp2_bars.png",
    "exp2_adaptive/exp2_renders.png",
    "exp3_global_to_local/exp3_stages.png",
    "exp3_global_to_local/exp3_strip.png",
    "exp4_cross_category/exp4_renders.png",
]


def main() -> int:
    from PIL import Image

    out = ROOT / "docs" / "img"
    out.mkdir(parents=True, exist_ok=True)
    total = 0
    for rel in sys.argv[1:] or IMAGES:
        src = ROOT / "results" / rel
        if not src.is_file():
            print(f"missing {src}, skipped", file=sys.stderr)
            continue
        dst = out / Path(rel).name
        Image.open(src).convert("RGB").quantize(colors=96, method=Image.Quantize.MEDIANCUT).save(dst, optimize=True)
        total += dst.stat().st_size
        print(f"{dst.relative_to(ROOT)}: {dst.stat().st_size // 1024} KB")
    print(f"total {total // 1024} KB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
