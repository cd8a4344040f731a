"""Pure plotting functions: data in, matplotlib ``Figure`` out (``save_figure`` writes a PNG).

No pyplot state: figures are ``matplotlib.figure.Figure`` objects drawn with the Agg canvas, so these
functions are safe in workers and headless runs. BEV plots are in metres with x (forward) to the right
and y (left) up; a BEV tensor [H, W] is shown with row 0 (ymin) at the bottom.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Sequence
from pathlib import Path

import matplotlib
import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .data.transforms import denormalize, project_to_image
from .files import atomic_path
from .geometry import BEVGrid

CLASS_COLORS = ("tab:orange", "tab:blue", "tab:green")  # divider, ped_crossing, boundary
CLASS_STYLES = ("-", "--", ":")  # the classes of elements coloured by track ID
DEFAULT_CLASSES = ("divider", "ped_crossing", "boundary")


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _class_color(label: int) -> str:
    return CLASS_COLORS[int(label) % len(CLASS_COLORS)]


def _bev_axes(ax, grid: BEVGrid, title: str, ego: bool = True) -> None:
    if ego:
        ax.plot([0], [0], marker=">", color="k", markersize=8)
    ax.set_xlim(grid.xmin, grid.xmax)
    ax.set_ylim(grid.ymin, grid.ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    ax.set_title(title, fontsize=9)


def figure_rgb(fig: Figure, dpi: int = 100) -> np.ndarray:
    """The figure drawn as an RGB image [H, W, 3] uint8 (for video frames)."""
    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Write ``fig`` to ``path`` (its format from the suffix) atomically: a full disk names the file
    and leaves no half-written picture."""
    path = Path(path)
    with atomic_path(path, keep_suffix=True) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    return path


def bev_polylines_figure(
    polylines: Sequence[dict], grid: BEVGrid, classes: Sequence[str] = DEFAULT_CLASSES, title: str = ""
) -> Figure:
    """Polyline dicts (metres, ego frame) drawn by class; vertices as dots, closed shapes filled lightly."""
    fig = Figure(figsize=(10, 10 * (grid.ymax - grid.ymin) / (grid.xmax - grid.xmin) + 0.8))
    ax = fig.add_subplot()
    for poly in polylines:
        pts = _np(poly["pts"])
        color = _class_color(poly["label"])
        ax.plot(pts[:, 0], pts[:, 1], "-", color=color, linewidth=1.5)
        ax.plot(pts[:, 0], pts[:, 1], ".", color=color, markersize=3)
        if poly.get("closed"):
            ax.fill(pts[:, 0], pts[:, 1], color=color, alpha=0.12)
    for k, name in enumerate(classes):
        n = sum(int(p["label"]) == k for p in polylines)
        ax.plot([], [], "-", color=_class_color(k), label=f"{name} ({n})")
    ax.legend(loc="upper right", fontsize=8)
    _bev_axes(ax, grid, title or f"GT polylines ({len(polylines)})")
    return fig


def vertex_cells_figure(
    cells: torch.Tensor,
    vertices_px: torch.Tensor,
    labels: torch.Tensor,
    next_idx: torch.Tensor,
    grid: BEVGrid,
    title: str = "",
) -> Figure:
    """The vertex-cell target [Hc, Wc] (occupied cells shaded, cell grid lines) with the vertex graph:
    vertices [M, 2] px coloured by class and an arrow along each ``next`` edge."""
    S = grid.cell_size
    cells, verts = _np(cells), _np(vertices_px).astype(np.float64)
    labels, nxt = _np(labels), _np(next_idx)
    fig = Figure(figsize=(12, 12 * grid.H / grid.W + 0.8))
    ax = fig.add_subplot()
    occupied = (cells < S * S).astype(float)
    ax.imshow(occupied, origin="lower", extent=(grid.xmin, grid.xmax, grid.ymin, grid.ymax), cmap="Greys",
              vmin=0, vmax=4, interpolation="nearest")
    cell_m = S * grid.resolution
    if grid.Wc <= 120 and grid.Hc <= 120:
        for x in np.arange(grid.xmin, grid.xmax + 1e-6, cell_m):
            ax.axvline(x, color="0.85", linewidth=0.3)
        for y in np.arange(grid.ymin, grid.ymax + 1e-6, cell_m):
            ax.axhline(y, color="0.85", linewidth=0.3)
    pts = grid.px_to_m(verts)
    for i in np.flatnonzero(nxt >= 0):
        a, b = pts[i], pts[nxt[i]]
        ax.annotate("", xy=b, xytext=a, arrowprops={"arrowstyle": "->", "color": "0.3", "linewidth": 0.6})
    for k in np.unique(labels):
        sel = labels == k
        ax.plot(pts[sel, 0], pts[sel, 1], "o", color=_class_color(k), markersize=2.5)
    n_cells = int((cells < S * S).sum())
    _bev_axes(ax, grid, title or f"vertex cells: {n_cells} of {cells.size} occupied, {len(verts)} graph vertices, "
              f"{int((nxt >= 0).sum())} edges")
    return fig


def distance_figure(distance: torch.Tensor, grid: BEVGrid, classes: Sequence[str] = DEFAULT_CLASSES) -> Figure:
    """The per-class distance transform [K, H, W] (BEV pixels), one panel per class."""
    dist = _np(distance)
    K = dist.shape[0]
    fig = Figure(figsize=(8, K * 8 * grid.H / grid.W + 0.6 * K))
    for k in range(K):
        ax = fig.add_subplot(K, 1, k + 1)
        im = ax.imshow(dist[k], origin="lower", extent=(grid.xmin, grid.xmax, grid.ymin, grid.ymax),
                       cmap="magma_r", vmin=0, vmax=max(float(dist.max()), 1e-6), interpolation="nearest")
        fig.colorbar(im, ax=ax, fraction=0.02, pad=0.01, label="px")
        name = classes[k] if k < len(classes) else str(k)
        _bev_axes(ax, grid, f"distance transform: {name} (zero pixels: {int((dist[k] == 0).sum())})", ego=False)
    return fig


def _densify(pts: np.ndarray, step: float) -> np.ndarray:
    seg = np.diff(pts, axis=0)
    n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / step), 1).astype(int)
    t = np.concatenate([np.arange(k) / k for k in n])
    start = np.repeat(pts[:-1], n, axis=0)
    return np.concatenate([start + np.repeat(seg, n, axis=0) * t[:, None], pts[-1:]])


def _project_polyline(pts_m: np.ndarray, intrinsics, cam_to_ego_rot, cam_to_ego_trans, post_rot, post_tran,
                      image_hw: tuple[int, int], ground_z: float = 0.0) -> np.ndarray:
    """A BEV polyline [P, 2] (metres, on the plane z = ground_z) -> image pixels [P', 2] of one camera,
    densified every 0.25 m, NaN where the line is behind the camera or far outside the image."""
    h, w = image_hw
    pts = _densify(pts_m.astype(np.float64), 0.25)
    pts3 = torch.from_numpy(np.c_[pts, np.full(len(pts), ground_z)]).float()
    uv, depth = project_to_image(pts3, intrinsics.float(), cam_to_ego_rot.float(), cam_to_ego_trans.float(),
                                 post_rot.float(), post_tran.float())
    uv, depth = uv.numpy(), depth.numpy()
    ok = (depth > 0.5) & (uv[:, 0] > -w) & (uv[:, 0] < 2 * w) & (uv[:, 1] > -h) & (uv[:, 1] < 2 * h)
    return np.where(ok[:, None], uv, np.nan)  # NaNs break the line


def _camera_lines_figure(images: torch.Tensor, calibration: Sequence[torch.Tensor], camera_names: Sequence[str],
                         ground_z: float, extra_height: float, layers) -> Figure:
    """The V camera images [V, 3, h, w] (ImageNet-normalised) in a 2 x ceil(V/2) grid with polylines projected
    into each (``_project_polyline``); ``calibration``: the five tensors [V, ...] of ``project_to_image``,
    ``layers``: (polylines, polyline -> ``ax.plot`` keywords) drawn in order."""
    V, _, h, w = images.shape
    rgb = denormalize(images.detach().float().cpu()).permute(0, 2, 3, 1).numpy()
    calibration = [t.detach().cpu() for t in calibration]
    cols = (V + 1) // 2
    fig = Figure(figsize=(4.2 * cols, 2 * 4.2 * h / w + extra_height))
    for v in range(V):
        ax = fig.add_subplot(2, cols, v + 1)
        ax.imshow(rgb[v])
        for polylines, style in layers:
            for poly in polylines:
                uv = _project_polyline(_np(poly["pts"]), *(t[v] for t in calibration), (h, w), ground_z)
                ax.plot(uv[:, 0], uv[:, 1], **style(poly))
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_axis_off()
        ax.set_title(camera_names[v] if v < len(camera_names) else f"camera {v}", fontsize=8)
    return fig


def cameras_figure(
    images: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_to_ego_rot: torch.Tensor,
    cam_to_ego_trans: torch.Tensor,
    post_rot: torch.Tensor,
    post_tran: torch.Tensor,
    polylines: Sequence[dict] = (),
    camera_names: Sequence[str] = (),
    ground_z: float = 0.0,
) -> Figure:
    """The V camera images [V, 3, h, w] (ImageNet-normalised) in a 2 x ceil(V/2) grid, with the GT
    polylines (metres, ego frame, on the plane z = ground_z) projected through the calibration and
    post_rot/post_tran."""
    calibration = (intrinsics, cam_to_ego_rot, cam_to_ego_trans, post_rot, post_tran)
    fig = _camera_lines_figure(images, calibration, camera_names, ground_z, 0.8, [
        (polylines, lambda p: {"linestyle": "-", "color": _class_color(p["label"]), "linewidth": 1.2})])
    fig.subplots_adjust(wspace=0.02, hspace=0.12)
    return fig


def write_sample_pngs(
    sample: dict, grid: BEVGrid, out_dir: str | Path, classes: Sequence[str] = DEFAULT_CLASSES,
    camera_names: Sequence[str] = (),
) -> list[Path]:
    """The GT of one (uncollated) sample as PNGs in ``out_dir``: BEV polylines, vertex cells with the
    vertex graph, the distance transform per class, and the camera images with the GT projected from the
    sample's ground plane (``ground_height``)."""
    out = Path(out_dir)
    token = sample.get("sample_token", "")
    figs = {
        "bev_polylines.png": bev_polylines_figure(sample["gt_polylines"], grid, classes, f"GT polylines {token}"),
        "vertex_cells.png": vertex_cells_figure(sample["gt_vertex_cells"], sample["gt_vertices_px"],
                                                sample["gt_vertex_labels"], sample["gt_vertex_next"], grid),
        "distance.png": distance_figure(sample["gt_distance"], grid, classes),
        "cameras.png": cameras_figure(sample["images"], sample["intrinsics"], sample["cam_to_ego_rot"],
                                      sample["cam_to_ego_trans"], sample["post_rot"], sample["post_tran"],
                                      sample["gt_polylines"], camera_names, float(sample["ground_height"])),
    }
    # written to temporaries and renamed together: a kill part-way over an earlier show-gt of another sample mixed
    # both samples' pictures (only bev_polylines.png names its sample)
    with contextlib.ExitStack() as stack:
        for name, fig in figs.items():
            save_figure(fig, stack.enter_context(atomic_path(out / name, keep_suffix=True)))
    return [out / name for name in figs]


# --- predictions (``instagram-hdmap predict``) -----------------------------------------------------
# These figures show the BEV as a driver sees it: x (forward) up, y (left) to the left, in metres.


def _default_style(make_figure):
    """Draw with matplotlib's default style (nuscenes-devkit's map_api sets a seaborn style globally
    when it is imported, which would put grid lines over the BEV rasters)."""

    @functools.wraps(make_figure)
    def wrapper(*args, **kwargs):
        import matplotlib.style

        with matplotlib.style.context("default"):
            return make_figure(*args, **kwargs)

    return wrapper


def _upright_axes(ax, grid: BEVGrid, title: str) -> None:
    """BEV axes in metres with x forward pointing up and y left pointing left; ego marker at 0."""
    ax.set_xlim(grid.ymax, grid.ymin)  # inverted: +y (left) is on the left
    ax.set_ylim(grid.xmin, grid.xmax)
    ax.set_aspect("equal")
    ax.set_xlabel("y left (m)")
    ax.set_ylabel("x forward (m)")
    ax.set_title(title, fontsize=9)
    ax.plot([0], [0], marker="^", color="k", markersize=7, linestyle="none")


def _upright_image(ax, image: np.ndarray, grid: BEVGrid, **kwargs):
    """A BEV raster [H, W] (rows along y, columns along x) on upright axes (call before _upright_axes)."""
    return ax.imshow(image.T, origin="lower", extent=(grid.ymin, grid.ymax, grid.xmin, grid.xmax),
                     interpolation="nearest", **kwargs)


def _upright_panel_size(grid: BEVGrid, height: float) -> tuple[float, float]:
    """(width, height) in inches of one upright BEV panel of the given height."""
    aspect = (grid.ymax - grid.ymin) / (grid.xmax - grid.xmin)
    return max(height * aspect, 1.5), height


def _track_color(track_id: int) -> tuple:
    """A colour per track ID: tab20's, stepped by 7 so that neighbouring IDs differ."""
    return matplotlib.colormaps["tab20"]((int(track_id) * 7) % 20)


def _tracked(polylines: Sequence[dict]) -> bool:
    return bool(polylines) and all(p.get("track_id") is not None for p in polylines)


def _upright_polylines(ax, polylines: Sequence[dict], linestyle: str = "-", scored: bool = False) -> None:
    """Polyline dicts (metres) by class, or (all carrying a ``track_id``) by track, each ID written at its first
    point and its class drawn as the line style; closed shapes filled lightly; ``scored``: opacity = score."""
    tracked = _tracked(polylines)
    for poly in polylines:
        pts = _np(poly["pts"])
        color = _track_color(poly["track_id"]) if tracked else _class_color(poly["label"])
        style = CLASS_STYLES[int(poly["label"]) % len(CLASS_STYLES)] if tracked else linestyle
        alpha = float(np.clip(0.2 + 0.8 * float(poly.get("score", 1.0)), 0.2, 1.0)) if scored else 1.0
        ax.plot(pts[:, 1], pts[:, 0], style, color=color, linewidth=1.6, alpha=alpha)
        ax.plot(pts[:, 1], pts[:, 0], ".", color=color, markersize=3.5, alpha=alpha)
        if poly.get("closed"):
            ax.fill(pts[:, 1], pts[:, 0], color=color, alpha=0.12 * alpha)
        if tracked and len(pts):
            ax.annotate(str(poly["track_id"]), (pts[0, 1], pts[0, 0]), fontsize=6, color=color)


def _class_legend(ax, classes: Sequence[str], counts: Sequence[int] | None = None, marker: str = "-",
                  tracked: bool = False) -> None:
    for k, name in enumerate(classes):
        label = name if counts is None else f"{name} ({counts[k]})"
        if tracked:  # the colours are the tracks': the classes are the line styles
            ax.plot([], [], CLASS_STYLES[k % len(CLASS_STYLES)], color="0.3", label=label)
        else:
            ax.plot([], [], marker, color=_class_color(k), label=label)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)


def _counts(polylines: Sequence[dict], num_classes: int) -> list[int]:
    return [sum(int(p["label"]) == k for p in polylines) for k in range(num_classes)]


@_default_style
def prediction_bev_figure(
    predictions: Sequence[dict],
    ground_truth: Sequence[dict] | None,
    grid: BEVGrid,
    classes: Sequence[str] = DEFAULT_CLASSES,
    title: str = "",
) -> Figure:
    """Predicted polylines (metres, with ``score``) next to the GT on the same upright axes
    (x forward up, y left); the prediction alone where ``ground_truth`` is None (your own images). A
    prediction's line opacity is its confidence."""
    w, h = _upright_panel_size(grid, 7.0)
    panels = [(predictions, "prediction", True)] + ([] if ground_truth is None else [(ground_truth, "ground truth",
                                                                                       False)])
    fig = Figure(figsize=(len(panels) * w + 1.2, h + 0.9), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(panels), sharex=True, sharey=True))
    for ax, (polys, name, scored) in zip(axes, panels):
        _upright_polylines(ax, polys, scored=scored)
        _class_legend(ax, classes, _counts(polys, len(classes)), tracked=_tracked(polys))
        extra = (" (opacity = confidence" + (", colour = track ID)" if _tracked(polys) else ")")) if scored else ""
        _upright_axes(ax, grid, f"{name}: {len(polys)} instances{extra}")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


@_default_style
def intermediate_figure(
    heatmap: np.ndarray | torch.Tensor,
    distance: np.ndarray | torch.Tensor | None,
    vertices_px: np.ndarray | torch.Tensor,
    vertex_labels: np.ndarray | torch.Tensor,
    edges: np.ndarray | torch.Tensor,
    edge_kept: np.ndarray | torch.Tensor,
    grid: BEVGrid,
    classes: Sequence[str] = DEFAULT_CLASSES,
    dt_clip: float = 10.0,
    title: str = "",
) -> Figure:
    """The intermediate results of the paper's Fig. 6 on upright BEV panels: the vertex heatmap [H, W], the distance
    transform per class [K, H, W] (BEV pixels; None: a model without a distance head, no panel), the real vertices
    [N, 2] (u, v) coloured by their GNN class [N], and the adjacency: ``edges`` [E, 2] vertex index pairs whose
    assignment probability exceeds the match threshold, ``edge_kept`` [E] bool for those the post-processing
    follows (mutual); the others are drawn dashed red. The heatmap is shown through a 3 x 3 max filter so that
    single-pixel peaks stay visible."""
    from matplotlib.collections import LineCollection
    from matplotlib.ticker import MaxNLocator

    heat = torch.as_tensor(_np(heatmap), dtype=torch.float32)
    heat = torch.nn.functional.max_pool2d(heat[None, None], 3, stride=1, padding=1)[0, 0].numpy()
    dist = None if distance is None else _np(distance).astype(np.float64)
    pts = grid.px_to_m(_np(vertices_px).astype(np.float64).reshape(-1, 2))
    labels = _np(vertex_labels).astype(np.int64).reshape(-1)
    edges, kept = _np(edges).astype(np.int64).reshape(-1, 2), _np(edge_kept).astype(bool).reshape(-1)
    n_dt = 0 if dist is None else dist.shape[0]  # distance-transform panels
    K = len(classes) if dist is None else n_dt
    panels = n_dt + 3
    cols = panels if (grid.xmax - grid.xmin) >= 1.5 * (grid.ymax - grid.ymin) else (panels + 1) // 2
    rows = -(-panels // cols)
    w, h = _upright_panel_size(grid, 6.0 if rows == 1 else 4.5)
    fig = Figure(figsize=(cols * (w + 0.35) + 0.6, rows * (h + 1.5) + 0.5), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True).reshape(-1)
    for ax in axes[panels:]:
        ax.set_axis_off()

    names = [classes[k] if k < len(classes) else str(k) for k in range(K)]
    heat_max = max(float(heat.max()), 1e-6)
    rasters = [(heat, "magma", heat_max, "vertex probability", f"vertex heatmap, 3x3 max filter (peak {heat_max:.2f})")]
    rasters += [(dist[k], "magma_r", dt_clip, "distance (BEV px)", f"distance transform: {names[k]}")
                for k in range(n_dt)]
    for ax, (image, cmap, vmax, label, panel_title) in zip(axes, rasters):
        im = _upright_image(ax, image, grid, cmap=cmap, vmin=0.0, vmax=vmax)
        cax = ax.inset_axes([0.0, -0.14, 1.0, 0.025])  # the colour bar below the axes, without shrinking them
        fig.colorbar(im, cax=cax, orientation="horizontal", label=label, ticks=MaxNLocator(4), format="%.3g")
        _upright_axes(ax, grid, panel_title)

    ax = axes[n_dt + 1]
    _upright_image(ax, heat, grid, cmap="Greys", vmin=0.0, vmax=2 * heat_max)
    for k in range(K):
        sel = labels == k
        ax.plot(pts[sel, 1], pts[sel, 0], "o", color=_class_color(k), markersize=3,
                label=f"{names[k]} ({int(sel.sum())})")
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    _upright_axes(ax, grid, f"{len(pts)} vertices by GNN class")

    ax = axes[n_dt + 2]
    ax.plot(pts[:, 1], pts[:, 0], "o", color="0.45", markersize=2.5, label=f"vertices ({len(pts)})")
    segments = pts[edges][..., ::-1]  # [E, 2 ends, (y, x)]
    ax.add_collection(LineCollection(segments[~kept], colors="tab:red", linewidths=0.8, linestyles="--",
                                     label=f"one-sided, dropped ({int((~kept).sum())})"))
    ax.add_collection(LineCollection(segments[kept], colors="k", linewidths=1.1,
                                     label=f"mutual, followed ({int(kept.sum())})"))
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    _upright_axes(ax, grid, "adjacency (p > match threshold)")
    for i, ax in enumerate(axes[:panels]):
        if i % cols:
            ax.set_ylabel("")
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


@_default_style
def prediction_cameras_figure(
    images: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_to_ego_rot: torch.Tensor,
    cam_to_ego_trans: torch.Tensor,
    post_rot: torch.Tensor,
    post_tran: torch.Tensor,
    predictions: Sequence[dict],
    ground_truth: Sequence[dict] = (),
    camera_names: Sequence[str] = (),
    classes: Sequence[str] = DEFAULT_CLASSES,
    ground_z: float = 0.0,
) -> Figure:
    """The V camera images [V, 3, h, w] (ImageNet-normalised; post_rot/post_tran map original pixels
    to them) with the predicted polylines (solid, by class) and the GT (white, dashed) projected from
    the ground plane z = ground_z of the ego frame through the calibration."""
    from matplotlib.lines import Line2D

    calibration = (intrinsics, cam_to_ego_rot, cam_to_ego_trans, post_rot, post_tran)
    fig = _camera_lines_figure(images, calibration, camera_names, ground_z, 1.1, [
        (predictions, lambda p: {"linestyle": "-", "color": _class_color(p["label"]), "linewidth": 1.8}),
        # the GT on top, thin, so both stay visible where they agree
        (ground_truth, lambda p: {"linestyle": "--", "color": "white", "linewidth": 0.8, "alpha": 0.9})])
    handles = [Line2D([], [], color=_class_color(k), linewidth=1.6, label=f"predicted {name}")
               for k, name in enumerate(classes)]
    handles.append(Line2D([], [], color="0.4", linestyle="--", linewidth=0.9, label="ground truth"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.subplots_adjust(wspace=0.02, hspace=0.12, bottom=0.08)
    return fig
