"""Where model A's squared error exceeds model B's, from two `radfield eval A B --compare` reports
(one per split) over the same views: per-view PSNR, the share of A's excess in the image border
(the outer 10 % of each side) and in bins of the ground truth's gradient magnitude (flattest half,
next 30 %, next 15 %, steepest 5 %). Reads the 8-bit renders and the grids' ground-truth panel.
    usage: .venv/bin/python scripts/study/excess_error.py A B REPORT_DIR...
    e.g.   excess_error.py x_fin_s1 x_gfin_s1 /work/runs/cmp_val /work/runs/cmp_test"""
import sys
from pathlib import Path

import cv2
import numpy as np


def read(path: Path) -> np.ndarray:
    return cv2.imread(str(path)).astype(np.float64) / 255


def main() -> None:
    a, b, reports = sys.argv[1], sys.argv[2], [Path(r) for r in sys.argv[3:]]
    errors_a, errors_b, gradients, borders = [], [], [], []
    for report in reports:
        for render_a in sorted((report / a / "renders").glob("*.png")):
            ra, rb = read(render_a), read(report / b / "renders" / render_a.name)
            grid = read(report / "grids" / render_a.name)
            h, w = ra.shape[:2]
            truth = grid[grid.shape[0] - h:, :w]            # the grid's first panel, under its caption
            ea, eb = ((ra - truth) ** 2).mean(-1), ((rb - truth) ** 2).mean(-1)
            print(f"{render_a.stem}: {a} {-10 * np.log10(ea.mean()):.2f} dB, {b} {-10 * np.log10(eb.mean()):.2f} dB")
            gray = cv2.cvtColor((truth * 255).astype(np.uint8), cv2.COLOR_BGR2GRAY).astype(np.float64)
            gradients.append(np.hypot(cv2.Sobel(gray, cv2.CV_64F, 1, 0), cv2.Sobel(gray, cv2.CV_64F, 0, 1)).ravel())
            border = np.zeros((h, w), bool)
            bh, bw = max(1, round(0.1 * h)), max(1, round(0.1 * w))
            border[:bh] = border[-bh:] = True
            border[:, :bw] = border[:, -bw:] = True
            errors_a.append(ea.ravel()), errors_b.append(eb.ravel()), borders.append(border.ravel())
    ea, eb, grad, border = (np.concatenate(x) for x in (errors_a, errors_b, gradients, borders))
    excess = (ea - eb).sum()
    print(f"border: {border.mean():.2f} of the pixels, {(ea - eb)[border].sum() / excess:.2f} of {a}'s excess squared error")
    bins = np.digitize(grad, np.quantile(grad, [0.5, 0.8, 0.95]))
    for k, label in enumerate(("flattest 50 %", "next 30 %", "next 15 %", "steepest 5 %")):
        m = bins == k
        print(f"{label}: {(ea - eb)[m].sum() / excess:.2f} of the excess; mean squared error {ea[m].mean():.2e} against {eb[m].mean():.2e}")


if __name__ == "__main__":
    main()
