"""Measuring a model on a dataset's views: the metrics (PSNR, SSIM, LPIPS), the evaluation of a
split (evaluate.py, which the eval stage and `radfield eval` run), its report and the comparison
of several runs."""
