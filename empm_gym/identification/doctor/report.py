"""Figures and ``report.md`` of the discrepancy doctor: plain arrays and dicts in, PNG / markdown out.

Inputs are metres; figures show millimetres. Figures reuse :func:`empm_gym.identification.report._plt`
and ``_save`` (Agg backend, tight layout, folders created).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Optional, Sequence, Tuple

import numpy as np

from ..report import _plt, _save

__all__ = ["PHASE_COLOURS", "plot_residual_timeline", "plot_residual_heatmap", "plot_candidate_gains",
           "plot_heldout_gap", "gap_rows", "gap_summary", "plot_rounds_gap", "rounds_rows", "rounds_section",
           "write_report_md"]

#: The metrics of the held-out gap (``doctor.json``'s ``gap``): key, axis label, factor from SI, higher is better.
GAP_METRICS = (("chamfer_m", "Chamfer (mm)", 1e3, False), ("track_median_m", "median tracking error (mm)", 1e3, False),
               ("track_rmse_m", "RMS tracking error (mm)", 1e3, False), ("mask_iou", "mask IoU (-)", 1.0, True))

#: Shading colour of each phase in the timeline.
PHASE_COLOURS = {
    "approach": "#d9d9d9",
    "contact": "#fdd49e",
    "holding": "#fc8d59",
    "moving": "#9ecae1",
    "after_release": "#c7e9c0",
    "at_rest": "#f0f0f0",
}


def plot_residual_timeline(frames_residual_base, frames_residual_best, phases, fit_frames: Optional[int], path,
                           title: str = "", fps: Optional[float] = None, labels: Tuple[str, str] = ("base model",
                                                                                                  "best candidate"),
                           hidden: Sequence[int] = ()):
    """Residual (mm) per frame with the phases shaded and named, and the held-out frames marked.

    Args:
        frames_residual_base: ``[T]`` per-frame residual of the base model (m), e.g. symmetric Chamfer.
        frames_residual_best: ``[T]`` same for the best candidate, or None.
        phases: :class:`~.phases.Phase` runs (anything with ``name``, ``start``, ``stop``).
        fit_frames: first held-out frame (frames ``>= fit_frames`` were not fitted); None: no marker.
        path: PNG to write; title: figure title; fps: adds a time axis (s) on top when given.
        hidden: frames where no camera sees the object (hatched: not scored, so no residual there).
    """
    plt = _plt()
    base = np.asarray(frames_residual_base, dtype=float) * 1e3
    T = len(base)
    fig, ax = plt.subplots(figsize=(10, 3.6))
    top = np.nanmax(base) if np.isfinite(base).any() else 1.0
    if frames_residual_best is not None:
        best = np.asarray(frames_residual_best, dtype=float) * 1e3
        if np.isfinite(best).any():
            top = max(top, np.nanmax(best))
    top = top if np.isfinite(top) and top > 0 else 1.0
    seen = set()
    for p in phases:
        c = PHASE_COLOURS.get(p.name, "#eeeeee")
        ax.axvspan(p.start - 0.5, p.stop - 0.5, color=c, alpha=0.6, lw=0,
                   label=None if p.name in seen else p.name.replace("_", " "))
        seen.add(p.name)
        if p.stop - p.start >= max(2, T // 40):
            wide = p.stop - p.start > T / 10  # a narrow phase's name stands upright, hanging from the top
            ax.text(0.5 * (p.start + p.stop - 1), top * (1.12 if wide else 1.47), p.name.replace("_", " "),
                    ha="center", va="bottom" if wide else "top", fontsize=7, rotation=0 if wide else 90)
    for i, f in enumerate(sorted(int(f) for f in hidden if 0 <= f < T)):
        ax.axvspan(f - 0.5, f + 0.5, facecolor="none", edgecolor="0.4", hatch="///", lw=0,
                   label="object hidden (not scored)" if i == 0 else None)
    t = np.arange(T)
    ax.plot(t, base, "-", color="k", lw=1.5, label=labels[0])
    if frames_residual_best is not None:
        ax.plot(t[:len(best)], best, "-", color="tab:red", lw=1.5, label=labels[1])
    if fit_frames is not None and 0 <= fit_frames < T:
        ax.axvline(fit_frames - 0.5, color="tab:blue", ls="--", lw=1.2)
        ax.annotate("held out \u2192", (fit_frames - 0.5, top * 0.98), xytext=(4, 0), textcoords="offset points",
                    color="tab:blue", fontsize=8, va="top")
        ax.annotate("\u2190 fitted", (fit_frames - 0.5, top * 0.98), xytext=(-4, 0), textcoords="offset points",
                    color="tab:blue", fontsize=8, va="top", ha="right")
    ax.set_xlim(-0.5, T - 0.5)
    ax.set_ylim(0, top * 1.5)
    ax.set_xlabel("frame")
    ax.set_ylabel("residual (mm)")
    if fps:
        sec = ax.secondary_xaxis("top", functions=(lambda f: f / fps, lambda s: s * fps))
        sec.set_xlabel("time (s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), framealpha=0.85)
    if title:
        ax.set_title(title)
    return _save(plt, fig, path)


def plot_residual_heatmap(points_by_frame: Mapping[str, Tuple[np.ndarray, np.ndarray]], path, title: str = "",
                          vmax_mm: Optional[float] = None):
    """Object points coloured by their residual (mm), one column per entry, top (x-y) and side (x-z) views.

    Args:
        points_by_frame: ``{label: (points [n, 3] m, residual [n] m)}``, e.g.
            ``{"frame 41, base": ..., "frame 41, refit": ...}``; columns keep this order.
        path: PNG to write. vmax_mm: top of the shared colour scale (default: 95th percentile of all).
    """
    plt = _plt()
    items = list(points_by_frame.items())
    n = max(1, len(items))
    allr = np.concatenate([np.asarray(r, dtype=float).ravel() for _, (_, r) in items]) * 1e3 if items else np.zeros(1)
    allr = allr[np.isfinite(allr)]
    vmax = vmax_mm if vmax_mm is not None else (float(np.percentile(allr, 95)) if len(allr) else 1.0)
    vmax = vmax if vmax > 0 else 1.0
    fig, axes = plt.subplots(2, n, figsize=(3.4 * n + 1.2, 4.4), squeeze=False)
    allp = [np.asarray(p, dtype=float).reshape(-1, 3) for _, (p, _) in items]
    allp = np.concatenate(allp) if allp and sum(len(p) for p in allp) else np.zeros((1, 3))
    lo, hi = allp.min(0), allp.max(0)
    pad = 0.05 * max(float(np.max(hi - lo)), 1e-3)
    sc = None
    for j, (label, (p, r)) in enumerate(items):
        p = np.asarray(p, dtype=float).reshape(-1, 3)
        r = np.asarray(r, dtype=float).ravel() * 1e3
        order = np.argsort(np.nan_to_num(r, nan=-1.0))  # worst on top
        for i, (a, b, nm) in enumerate(((0, 1, "top view: y (m)"), (0, 2, "side view: z (m)"))):
            ax = axes[i, j]
            sc = ax.scatter(p[order, a], p[order, b], c=r[order], s=4, cmap="inferno", vmin=0, vmax=vmax)
            ax.set_xlim(lo[a] - pad, hi[a] + pad)
            ax.set_ylim(lo[b] - pad, hi[b] + pad)
            ax.set_aspect("equal", adjustable="box")
            ax.set_xlabel("x (m)", fontsize=8)
            if j == 0:
                ax.set_ylabel(nm, fontsize=8)
            ax.tick_params(labelsize=7)
            if i == 0:
                ax.set_title(label, fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if sc is not None:
        cb = fig.colorbar(sc, ax=axes.ravel().tolist(), shrink=0.9)
        cb.set_label("residual: distance to the simulated body (mm)")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def plot_candidate_gains(names: Sequence[str], heldout_before, heldout_after, threshold: Optional[float], path,
                         title: str = "Held-out Chamfer per candidate effect"):
    """Bars of the held-out Chamfer (mm) before / after refitting each candidate, with the noise threshold.

    Args:
        names: candidate effect names.
        heldout_before: base model's held-out Chamfer (m): a scalar or one value per candidate.
        heldout_after: held-out Chamfer (m) after refitting with each candidate.
        threshold: smallest improvement (m) that counts as real (noise); drawn as a line at
            ``before - threshold`` per candidate: a bar must end below it. None: no line.
        path: PNG to write.
    """
    plt = _plt()
    names = list(names)
    n = len(names)
    before = np.broadcast_to(np.asarray(heldout_before, dtype=float), (n,)) * 1e3
    after = np.asarray(heldout_after, dtype=float).reshape(n) * 1e3
    x = np.arange(n)
    fig, ax = plt.subplots(figsize=(max(4.5, 1.3 * n + 2), 3.6))
    ax.bar(x - 0.2, before, 0.4, color="0.6", label="base model")
    gain_ok = np.isfinite(after) & (before - after >= (threshold * 1e3 if threshold is not None else 0.0))
    ax.bar(x + 0.2, after, 0.4, color=np.where(gain_ok, "tab:green", "tab:red").tolist(), label="refitted with effect")
    for i in range(n):
        if np.isfinite(after[i]) and np.isfinite(before[i]):
            ax.text(x[i] + 0.2, after[i], f"{before[i] - after[i]:+.2f}", ha="center", va="bottom", fontsize=7)
    if threshold is not None:
        lvl = before - threshold * 1e3
        ax.hlines(lvl, x - 0.45, x + 0.45, colors="k", linestyles="--", lw=1,
                  label=f"needed to count (gain \u2265 {threshold * 1e3:.2f} mm)")
    ax.set_xticks(x)
    ax.set_xticklabels([s.replace("_", "\n") for s in names], fontsize=8)
    ax.set_ylabel("held-out Chamfer (mm)")
    tops = np.concatenate([before[np.isfinite(before)], after[np.isfinite(after)], [1e-3]])
    ax.set_ylim(0, 1.35 * float(np.max(tops)))
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", ncol=3)
    return _save(plt, fig, path)


def plot_heldout_gap(gap: Mapping, path, title: str = ""):
    """The held-out gap per frame, one panel per metric of ``gap`` (``doctor.json``'s ``gap``): the base model
    against the model with the named effect (if any). Distances in mm, IoU unitless."""
    plt = _plt()
    frames = np.asarray(gap["frames"])
    per = gap["per_frame"]
    metrics = [m for m in GAP_METRICS if any(m[0] in per[k] for k in per)]
    fig, axes = plt.subplots(1, len(metrics), figsize=(3.4 * len(metrics), 3.2), squeeze=False)
    for ax, (key, label, scale, _) in zip(axes[0], metrics):
        for who, style, name in (("base", dict(color="k"), "base model"),
                                 ("effect", dict(color="tab:red"), f"with {gap.get('effect')}")):
            if who in per and key in per[who]:
                v = np.asarray([np.nan if x is None else x for x in per[who][key]], dtype=float) * scale
                ax.plot(frames, v, "o-", ms=3, lw=1.5, label=name, **style)
        ax.set_xlabel("held-out frame")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _save(plt, fig, path)


def gap_rows(gap: Mapping) -> list:
    """Rows of the held-out gap table: each metric's mean over the held-out frames with the base model and with
    the named effect, and the change (a lower distance or a higher IoU is better)."""
    rows = []
    tot = gap["total"]
    for key, label, scale, higher in GAP_METRICS:
        b = tot["base"].get(key)
        if b is None and key not in tot["base"]:
            continue
        row = {"metric": label, "base model": np.nan if b is None else b * scale}
        if "effect" in tot:
            e = tot["effect"].get(key)
            row[f"with {gap['effect']}"] = np.nan if e is None else e * scale
            if b is not None and e is not None and b != 0:
                change = 100.0 * (e - b) / abs(b)
                row["change [%]"] = change
                row["better"] = (change > 0) if higher else (change < 0)
        rows.append(row)
    return rows


def gap_summary(gap: Mapping) -> str:
    """One line of the held-out gap for a terminal: each metric with the base model -> with the named effect
    (the base model alone when no effect is named); "" without a gap."""
    tot = (gap or {}).get("total") or {}
    if "base" not in tot:
        return ""
    parts = []
    for key, label, scale, _ in GAP_METRICS:
        b = tot["base"].get(key)
        if b is None:
            continue
        name = label.split(" (")[0]
        unit = " mm" if scale != 1.0 else ""
        e = tot.get("effect", {}).get(key)
        parts.append(f"{name} {b * scale:.{1 if scale != 1.0 else 2}f}"
                     + (f" -> {e * scale:.{1 if scale != 1.0 else 2}f}" if e is not None else "") + unit)
    who = f"base model -> with {gap['effect']}" if "effect" in tot else "base model"
    return f"held-out frames, {who}: " + ", ".join(parts)


def rounds_rows(first: Mapping) -> list:
    """One row per round of a diagnosis in rounds (``first``: the first round's result, with ``rounds``): the
    effects its base model holds, that model's held-out Chamfer (mm), the verdict, the held-out Chamfer with it,
    the confidence and the round's report."""
    rows = [{"round": 1, "base model": "elastic", "held-out Chamfer, base model [mm]":
             1e3 * first["base"]["heldout"]["chamfer_m"], "verdict": first["effect"],
             "held-out Chamfer with it [mm]": _named_chamfer_mm(first), "confidence": first["confidence"],
             "report": "report.md"}]
    for r in first.get("rounds", ()):
        b = r.get("base_heldout_chamfer_m")
        e = r.get("effect_heldout_chamfer_m")
        rows.append({"round": r["round"], "base model": "elastic + " + " + ".join(r["base_effects"]),
                     "held-out Chamfer, base model [mm]": np.nan if b is None else 1e3 * b, "verdict": r["effect"],
                     "held-out Chamfer with it [mm]": np.nan if e is None else 1e3 * e,
                     "confidence": r["confidence"],
                     "report": "" if not r.get("dir") else f"{Path(r['dir']).name}/report.md"})
    return rows


def _named_chamfer_mm(result: Mapping) -> float:
    from .core import named_candidate

    c = named_candidate(result)
    return np.nan if c is None else 1e3 * c["heldout"]["chamfer_m"]


def plot_rounds_gap(rows: Sequence[Mapping], noise_sigma_m: float, path, title: str = ""):
    """Bars of the held-out Chamfer (mm) of the elastic model and of each model a round named (``rows``:
    :func:`rounds_rows`), the effects added left to right, with the depth noise as a line: what stays above it
    after the last round is what no effect of the catalogue explains."""
    plt = _plt()
    labels = ["elastic"]
    values = [rows[0]["held-out Chamfer, base model [mm]"]]
    for r in rows:
        if r["verdict"] != "none" and np.isfinite(r["held-out Chamfer with it [mm]"]):
            labels.append(f"+ {r['verdict'].replace('_', ' ')}\n(round {r['round']}, {r['confidence']:.2f})")
            values.append(r["held-out Chamfer with it [mm]"])
    x = np.arange(len(values))
    fig, ax = plt.subplots(figsize=(max(4.0, 1.8 * len(values) + 1.5), 3.6))
    ax.bar(x, values, 0.6, color=["0.6"] + ["tab:green"] * (len(values) - 1), label="held-out Chamfer")
    for i, v in enumerate(values):
        ax.text(x[i], v, f"{v:.2f}", ha="center", va="bottom", fontsize=8)
    ax.axhline(1e3 * noise_sigma_m, color="k", ls="--", lw=1, label=f"depth noise ({1e3 * noise_sigma_m:.2f} mm)")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=8)
    top = 1.25 * max(max(values), 1e3 * noise_sigma_m, 1e-3)
    low = min([v for v in values if v > 0] + [1e3 * noise_sigma_m])
    if top > 40.0 * low:  # a table friction takes 90 mm to 2: the later rounds' bars would not show
        ax.set_yscale("log")
        ax.set_ylim(0.5 * low, 2.0 * top)
        ax.set_ylabel("held-out Chamfer (mm, log scale)")
    else:
        ax.set_ylim(0, top)
        ax.set_ylabel("held-out Chamfer (mm)")
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(plt, fig, path)


def rounds_section(first: Mapping, rows: Sequence[Mapping], figure: str) -> str:
    """The markdown section of ``report.md`` on the later rounds (``rows``: :func:`rounds_rows`; ``figure``: the
    :func:`plot_rounds_gap` file beside the report)."""
    named = first.get("effects") or []
    lines = ["## Further rounds: the named effect in the base model, the catalogue's others tried again", "",
             "Each round's base model holds every effect named before it, their parameters fitted again with E in "
             "every fit of the round, and the round judges the catalogue's other effects by the same rules: it "
             "names another effect only if that still gains beyond noise, its penalty and the variants.", "",
             f"**Effects named: {', '.join(named) if named else 'none'}**", "", _table_md(rows)]
    for r in first.get("rounds", ()):
        lines += [f"- round {r['round']}: {r['effect']} ({r['confidence']:.2f}): {_fmt(r['reason'])}"]
        lines += [f"  - note: {_fmt(n)}" for n in r.get("notes", ())]
    lines += ["", f"![held-out Chamfer round by round]({figure})", ""]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- markdown


def _fmt(v) -> str:
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "n/a"
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e5):
            return f"{v:.3g}"
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x) for x in v)
    return str(v).replace("|", "\\|").replace("\n", " ")


def _table_md(rows) -> str:
    """A markdown table from a list of dicts (columns: union of keys) or a dict of dicts (row label first)."""
    if isinstance(rows, Mapping):
        rows = [{"": k, **(v if isinstance(v, Mapping) else {"value": v})} for k, v in rows.items()]
    rows = list(rows)
    if not rows:
        return "_(empty)_\n"
    cols = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    out = ["| " + " | ".join(str(c) for c in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        out.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(out) + "\n"


_HEADLINE_KEYS = ("headline", "summary", "effect", "verdict")


def write_report_md(path, verdict: Mapping, figures: Mapping[str, str], tables: Mapping[str, object],
                    title: str = "Discrepancy report", features: Optional[Mapping[str, float]] = None,
                    feature_info: Optional[Mapping[str, Tuple[str, str]]] = None,
                    notes: Optional[Sequence[str]] = None) -> Path:
    """Write a readable ``report.md``: verdict first, then tables (where, candidates, ...), features, figures.

    Args:
        verdict: plain dict; ``headline`` / ``summary`` / ``effect`` / ``verdict`` (first present) becomes
            the bold first line, every other entry a bullet ``key: value``.
        figures: ``{caption: path relative to the report}``, shown in this order.
        tables: ``{section title: rows}``; rows are a list of dicts or a dict of dicts (row label ->
            {column: value}); shown in this order (e.g. "Where the disagreement is", "Candidates").
        features: optional summary features (name -> value) and feature_info (name -> (unit, meaning)).
        notes: optional closing paragraphs.
    """
    lines = [f"# {title}", "", "## Verdict", ""]
    head = next((k for k in _HEADLINE_KEYS if k in verdict), None)
    if head is not None:
        lines += [f"**{_fmt(verdict[head])}**", ""]
    for k, v in verdict.items():
        if k != head:
            lines.append(f"- {k.replace('_', ' ')}: {_fmt(v)}")
    lines.append("")
    for name, rows in tables.items():
        lines += [f"## {name}", "", _table_md(rows)]
    if features:
        info = feature_info or {}
        rows = [{"feature": k, "value": v, "unit": info.get(k, ("", ""))[0], "meaning": info.get(k, ("", ""))[1]}
                for k, v in features.items()]
        lines += ["## Summary features (from the data alone)", "", _table_md(rows)]
    if figures:
        lines += ["## Figures", ""]
        for cap, rel in figures.items():
            lines += [f"### {cap}", "", f"![{cap}]({Path(rel).as_posix()})", ""]
    for n in notes or ():
        lines += [str(n), ""]
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text("\n".join(lines).rstrip() + "\n")
    return p
