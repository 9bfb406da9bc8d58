"""Evaluation reports: image grids, error heat maps and Markdown tables of metrics.json.

    error_map(render, photo)          mean absolute error over channels, coloured with `inferno` on a
                                      fixed scale [0, ERROR_SCALE] (so maps of different runs compare)
    view_grid(photo, render)          ground truth | render | error map | its colour bar, captioned
    side_by_side(photo, renders, labels)   ground truth | render A | render B | ..., labelled
    report_markdown(metrics, ...)     the report.md of one evaluation
    time_plot(per_time)               a dynamic scene's PSNR over time, as PNG bytes
    light_section(per_light)          a one-light-at-a-time capture's "Per light" section: the plot and
                                      the table of each light's position (or direction) and figures
    light_plot(per_light, centre, up) its PSNR per light, where each light stands about the object, as PNG bytes
    compare_markdown(rows)            the table of `radfield eval --compare`

Images are float (H, W, 3) numpy arrays in [0, 1]. No file is written here: that is for the
callers, through radfield.util.atomic.

TIME_PLOT (figures/psnr_over_time.png, beside report.md) is where a caller puts `time_plot`'s
picture; report_markdown links it when metrics has "per_time". Likewise LIGHT_PLOT
(figures/psnr_per_light.png) for `light_plot`'s, linked when metrics has "per_light".
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from radfield import conditions

ERROR_SCALE = 0.25  # |render − photo| (mean over RGB) shown at full brightness
GAP = 2             # white pixels between the panels of a grid
LABEL_HEIGHT = 14   # pixels of the caption row of a grid's panels
BAR_WIDTH, BAR_STRIP = 26, 8   # the colour bar panel of a view grid and its strip of colours
FIGURES = "figures"                         # the report's plots, beside report.md
TIME_PLOT = f"{FIGURES}/psnr_over_time.png"   # a dynamic scene's per-time PSNR (time_plot)
LIGHT_PLOT = f"{FIGURES}/psnr_per_light.png"  # a one-light-at-a-time capture's per-light PSNR (light_plot)


def error_map(render: np.ndarray, photo: np.ndarray) -> np.ndarray:
    """(H, W, 3) heat map of the per-pixel mean absolute error, 0 → black, ≥ ERROR_SCALE → yellow-white."""
    from matplotlib import colormaps

    err = np.abs(np.asarray(render, np.float32) - np.asarray(photo, np.float32)).mean(-1)
    return colormaps["inferno"](np.clip(err / ERROR_SCALE, 0.0, 1.0))[..., :3].astype(np.float32)


def hstack(panels: Sequence[np.ndarray], gap: int = GAP) -> np.ndarray:
    """Panels of equal height side by side, separated by white columns."""
    height = panels[0].shape[0]
    sep = np.ones((height, gap, 3), np.float32)
    out = [panels[0]]
    for panel in panels[1:]:
        out += [sep, panel]
    return np.concatenate([np.asarray(p, np.float32) for p in out], axis=1)


def view_grid(photo: np.ndarray, render: np.ndarray) -> np.ndarray:
    """Ground truth | render | error map | the error map's colour bar (0 to ERROR_SCALE), each with
    a caption row on top."""
    height = np.asarray(photo).shape[0]
    return hstack([_captioned(photo, "truth"), _captioned(render, "render"),
                   _captioned(error_map(render, photo), "|error|"), _captioned(colour_bar(height), "")])


def colour_bar(height: int, width: int = BAR_WIDTH) -> np.ndarray:
    """The error maps' scale as an (height, width, 3) panel: a vertical strip of their colours,
    ERROR_SCALE at the top, 0 at the bottom, with both values written beside it."""
    import cv2
    from matplotlib import colormaps

    strip = colormaps["inferno"](np.linspace(1.0, 0.0, height))[:, :3]
    panel = np.full((height, width, 3), 255, np.uint8)
    panel[:, :BAR_STRIP] = (strip[:, None, :] * 255).round().astype(np.uint8)
    for text, y in ((f"{ERROR_SCALE:g}", 8), ("0", height - 2)):
        cv2.putText(panel, text, (BAR_STRIP + 1, y), cv2.FONT_HERSHEY_SIMPLEX, 0.28, (0, 0, 0), 1, cv2.LINE_AA)
    return panel.astype(np.float32) / 255.0


def side_by_side(photo: np.ndarray, renders: Sequence[np.ndarray], labels: Sequence[str]) -> np.ndarray:
    """Ground truth then each render, with a caption row ("truth", labels...) on top."""
    panels = [_captioned(photo, "truth")] + [_captioned(r, label) for r, label in zip(renders, labels)]
    return hstack(panels)


def _captioned(img: np.ndarray, text: str) -> np.ndarray:
    import cv2

    img = np.asarray(img, np.float32)
    width = img.shape[1]
    caption = np.full((LABEL_HEIGHT, width, 3), 255, np.uint8)  # cv2 draws text on 8-bit images only
    scale = 0.35
    text = text.encode("ascii", "replace").decode()  # the Hershey fonts have ASCII only
    while text and cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] > width - 2:
        text = text[:-1]  # cut the caption until it fits the panel
    cv2.putText(caption, text, (1, LABEL_HEIGHT - 4), cv2.FONT_HERSHEY_SIMPLEX,
                scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([caption.astype(np.float32) / 255.0, img], axis=0)


# --- Markdown ---------------------------------------------------------------------------------


def _fmt(value: Any, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def human_bytes(size: int | None) -> str:
    if size is None:
        return "–"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size} B" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return str(size)


def report_markdown(metrics: dict[str, Any], *, model: str, grids_dir: str | None, curves: Sequence[str] = ()) -> str:
    """report.md: summary, the per-view table with its mean row, grids and training curves (links
    relative to the report's folder)."""
    m = metrics
    lines = [
        f"# Evaluation of {model}",
        "",
        f"{m['views']} {m['split']} views of {m['width']}×{m['height']} pixels; {m['kind']} primitives.",
        "",
        "| model | value |",
        "| --- | --- |",
        f"| primitives | {m['num_primitives']} |",
        f"| parameters | {m['num_params']} |",
        f"| file size | {human_bytes(m['file_size_bytes'])} ({m['file_size_bytes']} bytes) |",
        f"| FPS (rendering, {m['width']}×{m['height']}) | {m['fps']:.2f} |",
        "",
        "| view | PSNR (dB) | SSIM | LPIPS | seconds |",
        "| --- | --- | --- | --- | --- |",
    ]
    for v in m["per_view"]:
        lines.append(f"| {v['name']} | {v['psnr']:.2f} | {v['ssim']:.4f} | {_fmt(v.get('lpips'), 4)} | {v['seconds']:.3f} |")
    mean_seconds = sum(v["seconds"] for v in m["per_view"]) / max(len(m["per_view"]), 1)
    lines.append(f"| **mean** | **{m['psnr']:.2f}** | **{m['ssim']:.4f}** | **{_fmt(m.get('lpips'), 4)}** | "
                 f"**{mean_seconds:.3f}** |")
    lines.append("")
    if m.get("lpips") is None and m.get("lpips_note"):
        lines += [f"LPIPS not computed: {m['lpips_note']}.", ""]
    lines += ["PSNR over all pixels and channels (data range 1); SSIM with the 11×11 Gaussian window (σ = 1.5); "
              "LPIPS AlexNet v0.1 (lower is better).", ""]
    for condition in conditions.registered():   # a section per view condition the views carry
        rows = m.get(f"per_{condition.name}")
        if rows:
            section = SECTIONS.get(condition.name)
            lines += section(rows) if section is not None else condition_section(condition, rows)
    if grids_dir is not None:
        lines += ["## Views", "", f"ground truth | render | error |render − photo| (mean over RGB; black 0, "
                  f"yellow ≥ {ERROR_SCALE}) | the error's colour bar", ""]
        lines += [f"![{v['name']}]({grids_dir}/{v['name']}.png)" for v in m["per_view"]]
        lines.append("")
    if curves:
        lines += ["## Training", ""] + [f"![training curves]({c})" if c.endswith(".png") else f"- [{c}]({c})"
                                        for c in curves] + [""]
    return "\n".join(lines)


def time_section(per_time: Sequence[dict[str, Any]]) -> list[str]:
    """The report's "Over time" section of a dynamic scene: the plot and the per-time table."""
    lines = ["## Over time", "", f"![PSNR over time]({TIME_PLOT})", "",
             "| time | views | PSNR (dB) | SSIM | LPIPS |", "| --- | --- | --- | --- | --- |"]
    lines += [f"| {t['time']:.4g} | {t['views']} | {t['psnr']:.2f} | {t['ssim']:.4f} | {_fmt(t.get('lpips'), 4)} |"
              for t in per_time]
    return lines + [""]


def light_section(per_light: Sequence[dict[str, Any]]) -> list[str]:
    """The report's "Per light" section: the plot, then each light's position (or direction),
    intensity and figures."""
    lines = ["## Per light", "", f"![PSNR per light]({LIGHT_PLOT})", "",
             "| light | intensity | views | PSNR (dB) | SSIM | LPIPS |",
             "| --- | --- | --- | --- | --- | --- |"]
    for light in per_light:
        where = ("at " if "position" in light else "along ") + ", ".join(
            f"{x:.3g}" for x in light.get("position", light.get("direction")))
        lines.append(f"| {where} | {light['intensity']:.4g} | {light['views']} | {light['psnr']:.2f} | "
                     f"{light['ssim']:.4f} | {_fmt(light.get('lpips'), 4)} |")
    return lines + [""]


def condition_section(condition, rows: Sequence[dict[str, Any]]) -> list[str]:
    """The report's section of a view condition without one of its own (SECTIONS): the per-value table."""
    lines = [f"## Per {condition.name}", "", f"| {condition.name} | views | PSNR (dB) | SSIM | LPIPS |",
             "| --- | --- | --- | --- | --- |"]
    lines += [f"| {condition.label(condition.from_row(row))} | {row['views']} | {row['psnr']:.2f} | {row['ssim']:.4f} | "
              f"{_fmt(row.get('lpips'), 4)} |" for row in rows]
    return lines + [""]


# the sections with a plot of their own (evaluation/evaluate.write_report draws it), by condition
SECTIONS = {"time": time_section, "light": light_section}


def time_plot(per_time: Sequence[dict[str, Any]], title: str = "held-out views over time") -> bytes:
    """PNG bytes (matplotlib, Agg backend) of `time_figure`."""
    import io

    buffer = io.BytesIO()
    time_figure(per_time, title).savefig(buffer, format="png", dpi=100)
    return buffer.getvalue()


def time_figure(per_time: Sequence[dict[str, Any]], title: str = "held-out views over time"):
    """PSNR per moment ξ_t, the mean over its views, with the overall mean as a dashed line; the
    legend below the axes, where it hides no point (in the corner it hid the last moment's)."""
    import matplotlib

    matplotlib.use("Agg")  # no display; must precede pyplot
    from matplotlib.figure import Figure

    times, values = [t["time"] for t in per_time], [t["psnr"] for t in per_time]
    weights = [t["views"] for t in per_time]
    figure = Figure(figsize=(6, 3.6), layout="constrained")
    axes = figure.subplots()
    axes.plot(times, values, "o-", ms=3, lw=1.0, label="mean over the moment's views")
    axes.axhline(sum(v * w for v, w in zip(values, weights)) / sum(weights), ls="--", lw=0.8, color="grey",
                 label="mean over all views")
    axes.set(title=title, xlabel="time ξ", ylabel="PSNR (dB)", xlim=(-0.02, 1.02))
    figure.legend(loc="outside lower center", ncols=2, fontsize="small")
    return figure


def light_angles(per_light: Sequence[dict[str, Any]], centre, up) -> list[tuple[float, float]]:
    """(azimuth, elevation) in degrees of each light about `centre` (its direction from there, a
    directional light's the reverse of its "direction"), elevation above the plane normal to `up`:
    conditions/light.light_angles, the angles of `--light-orbit` and the viewer's sliders."""
    from radfield.core.geometry.cameras import Light
    from radfield.conditions.light import light_angles as angles

    return [angles(centre, up, Light(light.get("position"), light.get("direction")))[:2] for light in per_light]


def light_plot(per_light: Sequence[dict[str, Any]], centre=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0),
               title: str = "held-out views per light") -> bytes:
    """PNG bytes (matplotlib, Agg backend): each light's PSNR (the mean over its views) as a dot
    coloured by PSNR where the light stands about the object (left: a sky map, azimuth round the
    `up` axis, the zenith in the middle, the horizon on the ring marked 0° and lights below it
    outside that ring), and PSNR against the light's elevation (right), the overall mean dashed.
    Point lights are dots, directional ones triangles."""
    import io

    import matplotlib

    matplotlib.use("Agg")  # no display; must precede pyplot
    from matplotlib.figure import Figure

    angles = np.array(light_angles(per_light, centre, up), dtype=np.float64).reshape(-1, 2)
    values = np.array([light["psnr"] for light in per_light])
    weights = np.array([light["views"] for light in per_light])
    point = np.array(["position" in light for light in per_light])
    low, high = float(values.min()), float(max(values.max(), values.min() + 1e-3))
    figure = Figure(figsize=(8, 3.6), layout="constrained")
    sky = figure.add_subplot(1, 2, 1, projection="polar")
    versus = figure.add_subplot(1, 2, 2)
    for mask, marker in ((point, "o"), (~point, "^")):
        if mask.any():
            dots = sky.scatter(np.radians(angles[mask, 0]), 90.0 - angles[mask, 1], c=values[mask], cmap="viridis",
                               vmin=low, vmax=high, marker=marker, s=28, edgecolors="k", linewidths=0.4)
            versus.scatter(angles[mask, 1], values[mask], c=values[mask], cmap="viridis", vmin=low, vmax=high,
                           marker=marker, s=22, edgecolors="k", linewidths=0.4)
    sky.set_rlim(0, max(90.0, float((90.0 - angles[:, 1]).max()) + 5))   # below the horizon: outside the ring
    sky.set_rticks([30, 60, 90])
    sky.set_yticklabels(["60°", "30°", "0°"], fontsize="x-small")   # the elevation of each ring
    sky.set_rlabel_position(157.5)   # between the 135° and 180° spokes, clear of the azimuth labels
    sky.tick_params(axis="x", labelsize="x-small")
    sky.set_title("where each light stands (azimuth; elevation 90° at the centre)", fontsize="small")
    figure.colorbar(dots, ax=sky, label="PSNR (dB)", shrink=0.8)
    versus.axhline(float((values * weights).sum() / weights.sum()), ls="--", lw=0.8, color="grey",
                   label="mean over all views")
    versus.set(title=title, xlabel="light elevation (degrees)", ylabel="PSNR (dB)")
    versus.legend(loc="best", fontsize="small")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100)
    return buffer.getvalue()


COMPARE_COLUMNS = ("run", "kind", "PSNR (dB)", "SSIM", "LPIPS", "primitives", "parameters", "size", "FPS", "train time")


def compare_markdown(rows: Sequence[dict[str, Any]], *, split: str, views: int, grids_dir: str | None) -> str:
    """The `eval --compare` table. rows: {"label", "metrics" (metrics.json), "train_seconds" or None}."""
    lines = [f"# Comparison on {views} {split} views", "",
             "| " + " | ".join(COMPARE_COLUMNS) + " |", "|" + " --- |" * len(COMPARE_COLUMNS)]
    for row in rows:
        m = row["metrics"]
        seconds = row.get("train_seconds")
        lines.append(f"| {row['label']} | {m['kind']} | {m['psnr']:.2f} | {m['ssim']:.4f} | {_fmt(m.get('lpips'), 4)} | "
                     f"{m['num_primitives']} | {m['num_params']} | {human_bytes(m['file_size_bytes'])} | "
                     f"{m['fps']:.2f} | {'–' if seconds is None else f'{seconds:.0f} s'} |")
    lines.append("")
    if grids_dir is not None:
        lines += ["## Views", "", "truth | " + " | ".join(r["label"] for r in rows), ""]
        lines += [f"![{v['name']}]({grids_dir}/{v['name']}.png)" for v in rows[0]["metrics"]["per_view"]]
        lines.append("")
    return "\n".join(lines)

