"""A self-contained ``report.html`` of a diagnosis: text, tables and plots (base64 PNG).

One file, no external resources: it can be mailed or archived as is. Every figure is also
available as a function returning a matplotlib Figure (``fig_*``), for notebooks.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import numpy as np

from aqfg.diagnose.conditions import UNITS
from aqfg.diagnose.confirm import MIN_GAIN


def _plt():
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    return plt


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    _plt().close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


# ---------------------------------------------------------------- figures
def fig_map(diag, i: int = 0):
    """Map of mission ``i``: fixes, fitted track, model-only legs between fit fixes (base
    model, and with the best effect when one is found)."""
    plt = _plt()
    m = diag.missions[i]
    fig, ax = plt.subplots(figsize=(7, 6))
    tr = diag.base.full.missions[i].track
    ax.plot(tr.pos[:, 1], tr.pos[:, 0], color="0.6", lw=1, label="fitted track (all fixes)")
    if diag.base.next_fix:
        h = diag.base.next_fix[i]
        u = h.used
        ax.scatter(h.fix_ne[u, 1], h.fix_ne[u, 0], s=6, c="k", label="held-out fixes", zorder=3)
        for j, leg in enumerate(h.legs):
            ax.plot(leg.pos[:, 1], leg.pos[:, 0], color="tab:red", lw=1,
                    label="model only, between fit fixes" if j == 0 else None)
        best = diag.best
        if best is not None and best.refit is not None and best.refit.next_fix:
            for j, leg in enumerate(best.refit.next_fix[i].legs):
                ax.plot(leg.pos[:, 1], leg.pos[:, 0], color="tab:green", lw=1,
                        label=f"model + {best.effect}" if j == 0 else None)
    from aqfg.diagnose.compare import fixes_of
    fx = fixes_of(_fit_mission(diag, i))
    ax.scatter(fx.ne[:, 1], fx.ne[:, 0], s=18, facecolors="none", edgecolors="tab:blue",
               label="fit fixes", zorder=4)
    _finish_map(ax, m, "fixes and the model-only track between them")
    return fig


def _finish_map(ax, m, title: str) -> None:
    """The mission's map axes finished: its USBL station (if any), east/north labels (m),
    equal scale, ``title`` after the mission's name, the legend."""
    if m.usbl_station is not None:
        ax.plot(m.usbl_station[1], m.usbl_station[0], "k^", ms=9, label="USBL station")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{m.name}: {title}")
    ax.legend(fontsize=8, loc="best")


def _fit_mission(diag, i):
    from aqfg.diagnose.compare import split_fixes
    return split_fixes(diag.missions[i], diag.settings.get("gnss_every", 8.0)).fit


# the components a surface vehicle does not have (Mission.planar: it stays on the surface)
VERTICAL = ("down", "vd", "depth")


def for_vehicle(series, mission) -> list:
    """``series`` (:class:`aqfg.diagnose.compare.SensorSeries`) without the axes the vehicle
    of ``mission`` does not have (a surface vehicle: depth and vertical motion), dropping a
    sensor left with none."""
    from dataclasses import replace
    if not mission.planar:
        return list(series)
    out = []
    for s in series:
        keep = np.array([lab not in VERTICAL for lab in s.labels], bool)
        if not keep.any():
            continue
        def sel(a, keep=keep):
            return None if a is None else a[:, keep]
        out.append(replace(s, measured=sel(s.measured), predicted=sel(s.predicted),
                           raw=s.raw[:, keep], normalised=s.normalised[:, keep],
                           labels=tuple(np.array(s.labels)[keep]),
                           units=tuple(np.array(s.units)[keep])))
    return out


def fig_sensors(diag, i: int = 0):
    """Per sensor of mission ``i``: measured vs predicted, and normalised residuals (the
    axes the vehicle has)."""
    plt = _plt()
    series = for_vehicle(diag.series[diag.missions[i].name], diag.missions[i])
    rows = sum(s.raw.shape[1] for s in series)
    fig, axes = plt.subplots(rows, 2, figsize=(11, 2.0 * rows + 0.5), squeeze=False)
    r = 0
    for s in series:
        for c in range(s.raw.shape[1]):
            a0, a1 = axes[r]
            lab = f"{s.sensor} {s.labels[c]}"
            if s.measured is not None and s.predicted is not None:
                a0.plot(s.t, s.measured[:, c], ".", ms=2, color="k", label="measured")
                a0.plot(s.t, s.predicted[:, c], "-", lw=1, color="tab:red", label="model")
            else:
                a0.plot(s.t, s.raw[:, c], ".", ms=2, color="k", label="residual")
            a0.set_ylabel(f"{lab} ({s.units[c]})", fontsize=8)
            a0.legend(fontsize=7, loc="upper right")
            a1.plot(s.t, s.normalised[:, c], ".", ms=2, color="tab:blue")
            for k in (-3, 3):
                a1.axhline(k, color="0.6", ls="--", lw=0.8)
            a1.set_ylabel(f"{lab} / sigma", fontsize=8)
            r += 1
    axes[0, 0].set_title("measured vs predicted (model fitted to all fixes)")
    axes[0, 1].set_title("normalised residual (±3 sigma dashed)")
    for a in axes[-1]:
        a.set_xlabel("t (s)")
    fig.tight_layout()
    return fig


def fig_consistency(diag):
    """Windowed NIS of the held-out fixes vs the chi-square band: model, and with the best
    effect."""
    plt = _plt()
    tests = [("model", diag.base.consistency)]
    if diag.before is not None:
        tests.insert(0, (diag.before.label, diag.before.consistency))
    best = diag.best
    if best is not None and best.refit is not None:
        tests.append((f"+ {best.effect}", best.refit.consistency))
    fig, axes = plt.subplots(len(tests), 1, figsize=(10, 2.4 * len(tests)), squeeze=False)
    for ax, (lab, c) in zip(axes[:, 0], tests):
        if c is None:
            continue
        mid = 0.5 * (c.t0 + c.t1)
        w = c.t1 - c.t0
        ax.bar(mid, c.nis / c.dof, width=0.9 * w, color=np.where(c.fails, "tab:red", "tab:blue"))
        ax.hlines(c.upper / c.dof, c.t0, c.t1, color="k", ls="--", lw=1,
                  label=f"{100 * (1 - c.alpha / 2):.1f}% band")
        ax.hlines(c.lower / c.dof, c.t0, c.t1, color="k", ls=":", lw=1)
        ax.axhline(1.0, color="0.5", lw=0.8)
        ax.set_ylabel("NIS / dof")
        ax.set_title(f"{lab}: {c.summary()}", fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    return fig


def _compared_fits(diag) -> list:
    """The fits a before/after figure compares: without the user-added effects (if any),
    the model as given, and with the best confirmed candidate (if any)."""
    evs = [diag.before] if diag.before is not None else []
    evs.append(diag.base)
    if diag.best is not None and diag.best.refit is not None:
        evs.append(diag.best.refit)
    return evs


def fig_growth(diag, evs=None):
    """Dead-reckoning error vs time since the last fit fix (held-out fixes), for the fits
    ``evs`` (default: the ones the diagnosis compares)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    evs = _compared_fits(diag) if evs is None else evs
    for ev in evs:
        if not ev.long:
            continue
        dt = np.concatenate([h.dt[h.used] for h in ev.long])
        e = np.concatenate([h.err[h.used] for h in ev.long])
        if not len(dt):
            continue
        bins = np.linspace(0, dt.max() + 1e-9, 11)
        j = np.clip(np.digitize(dt, bins) - 1, 0, 9)
        n = np.bincount(j, minlength=10)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(np.bincount(j, e ** 2, minlength=10) / n)
        ax.plot(0.5 * (bins[:-1] + bins[1:]), rms, "o-",
                label=f"{ev.label} (RMS {ev.rmse_raw:.2f} m)")
    noise = (np.concatenate([h.noise[h.used] for h in diag.base.long]) if diag.base.long
             else np.zeros(0))
    if len(noise):
        ax.axhline(math.sqrt(float(np.mean(noise))), color="0.5", ls="--", lw=1,
                   label="fix noise alone")
    ax.set_xlabel("time since the fit fix the model started from (s)")
    ax.set_ylabel("RMS distance to held-out fixes (m)")
    ax.set_title("growth of the dead-reckoning error between fixes")
    ax.legend(fontsize=8)
    return fig


def fig_heldout_time(diag, i: int = 0, evs=None):
    """Held-out innovation distance over time (model vs model + best effect, or ``evs``)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 3))
    for ev in (_compared_fits(diag) if evs is None else evs):
        if ev.long:
            h = ev.long[i]
            ax.plot(h.t[h.used], h.err[h.used], ".", ms=3, label=ev.label)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("dead-reckoned - fix (m)")
    ax.set_title(f"{diag.missions[i].name}: held-out fixes, model-only prediction error")
    ax.legend(fontsize=8)
    return fig


def fig_residuals_compare(diag, i: int = 0, window: float = 30.0):
    """Normalised residuals of the fitted models over time (NIS per dof in ``window``-s
    bins, per sensor): before/after an added effect, or the model vs the model with the
    best candidate."""
    plt = _plt()
    from aqfg.diagnose.compare import sensor_series
    evs = _compared_fits(diag)
    if len(evs) < 2:
        return None
    mission = diag.missions[i]
    sensors = [s.sensor for s in for_vehicle(sensor_series(diag.base.full.missions[i]), mission)]
    fig, axes = plt.subplots(len(sensors), 1, figsize=(10, 2.2 * len(sensors)), squeeze=False)
    for ax, name in zip(axes[:, 0], sensors):
        for ev in evs:
            ss = {s.sensor: s for s in for_vehicle(sensor_series(ev.full.missions[i]), mission)}
            if name not in ss:
                continue
            s = ss[name]
            edges = np.arange(s.t.min(), s.t.max() + window, window)
            j = np.clip(np.digitize(s.t, edges) - 1, 0, len(edges) - 2)
            nis = np.nansum(np.clip(s.normalised, -5, 5) ** 2, axis=1)    # outliers clipped
            num = np.bincount(j, nis, len(edges) - 1)
            den = np.bincount(j, s.dof, len(edges) - 1)
            with np.errstate(invalid="ignore", divide="ignore"):
                ax.step(edges[:-1], num / den, where="post", label=ev.label)
        ax.set_ylabel(f"{name}: NIS / dof", fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
    axes[0, 0].set_title(f"{diag.missions[i].name}: residuals of the fits to all fixes, "
                         f"{window:.0f}-s means (components clipped at 5 sigma)")
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    return fig


def fig_conditions(diag, max_panels: int = 6):
    """Mean NIS per dof by condition quartile for the strongest condition tests."""
    plt = _plt()
    eff = sorted(diag.conditions, key=lambda e: e.p_adjusted)[:max_panels]
    if not eff:
        return None
    n = len(eff)
    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    for ax, e in zip(axes.flat, eff):
        x = e.bin_centres
        if e.condition == "heading":
            x = np.degrees(x)
        ax.bar(np.arange(len(x)), e.binned, color="tab:red" if e.p_adjusted < 0.05 else "tab:blue")
        ax.set_xticks(np.arange(len(x)))
        ax.set_xticklabels([f"{v:.3g}" for v in x], fontsize=7)
        ax.axhline(1.0, color="0.5", lw=0.8)
        unit = "deg" if e.condition == "heading" else UNITS.get(e.condition, "")
        ax.set_xlabel(f"{e.condition} ({unit})", fontsize=8)
        ax.set_ylabel("mean NIS / dof", fontsize=8)
        ax.set_title(f"{e.series}: rho={e.rho:.2f}, p={e.p_adjusted:.2g}", fontsize=8)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.tight_layout()
    return fig


_STATUS_COLOUR = {"missing": "tab:green", "independent": "tab:orange", "echo": "tab:blue",
                  "rejected": "tab:red", "not significant": "0.6"}


def fig_ranking(diag):
    """Score-test evidence (-log10 p, Holm) and refit BIC change per candidate, coloured by
    status (green missing, orange independent evidence, blue echo, red not confirmed)."""
    plt = _plt()
    r = diag.ranking
    if not r:
        return None
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 0.35 * len(r) + 1.5))
    names = [c.effect for c in r][::-1]
    lp = [min(-math.log10(max(c.p_adjusted, 1e-300)), 300) for c in r][::-1]
    col = [_STATUS_COLOUR.get(c.status, "0.6") for c in r][::-1]
    a0.barh(names, lp, color=col)
    a0.axvline(-math.log10(diag.settings.get("alpha", 0.01)), color="k", ls="--", lw=1)
    a0.set_xlabel("score test: -log10 p (Holm)")
    db = [c.dbic if np.isfinite(c.dbic) else 0.0 for c in r][::-1]
    a1.barh(names, db, color=col)
    a1.axvline(0, color="k", lw=0.8)
    a1.set_xlabel("refit: BIC change (negative favours the effect)")
    fig.tight_layout()
    return fig


# ---------------------------------------------------------------- HTML
_CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;font-size:13px}
td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#eee}td.l{text-align:left}
.verdict{font-size:17px;padding:10px;background:#f4f4e8;border-left:5px solid #aa5}
pre{background:#f6f6f6;padding:8px;font-size:12px;overflow-x:auto}img{max-width:100%}"""


def _img(fig) -> str:
    if fig is None:
        return ""
    return f'<p><img alt="figure" src="data:image/png;base64,{_png(fig)}"></p>'


def _beyond(ev) -> str:
    """An evaluation's dead-reckoning error beyond the held-out fixes' noise (m), or
    "within the noise"."""
    return f"{ev.rmse:.2f}" if ev.rmse > 0 else "within the noise"


def _gain(c) -> str:
    from aqfg.diagnose.wording import gain_cell
    return html.escape(gain_cell(c))


def _fmt(x, f=".3g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return format(x, f)


def ranking_table(diag) -> str:
    rows = ["<tr><th>rank</th><th>effect</th><th>score (LM)</th><th>p (Holm)</th>"
            "<th>robust p</th><th>dBIC</th><th>held-out dLL</th><th>bootstrap first</th>"
            "<th>held-out RMS before → after (m; gain beyond the noise floor)</th>"
            "<th>consistent after</th><th>estimate ± sigma</th><th>status</th></tr>"]
    best = diag.best.effect if diag.best is not None else None
    for i, c in enumerate(diag.ranking, 1):
        est = "<br>".join(f"{html.escape(n)} = {v['value']:.4g} ± {v['sigma']:.2g}"
                          for n, v in c.estimate().items())
        ho = c.refit is not None and c.refit.has_heldout
        dr = (f"{diag.base.rmse_raw:.2f} → {c.refit.rmse_raw:.2f} ({_gain(c)})" if ho else "–")
        cons = ("pass" if c.refit.consistency.passed else "FAIL") if ho else "–"
        v = html.escape(c.status_text(best))
        if c.gain is not None and math.isfinite(c.gain.p):
            v += f" (held-out p = {c.gain.p:.2g})"
        rows.append(f"<tr><td>{i}</td><td class=l>{html.escape(c.effect)}</td>"
                    f"<td>{_fmt(c.score.statistic, '.1f')}</td><td>{_fmt(c.p_adjusted, '.2g')}</td>"
                    f"<td>{_fmt(c.score.p_value_robust, '.2g')}</td><td>{_fmt(c.dbic, '.1f')}</td>"
                    f"<td>{_fmt(c.dll, '.1f')}</td>"
                    f"<td>{_fmt(c.bootstrap_first, '.2f')}</td><td>{dr}</td><td>{cons}</td>"
                    f"<td class=l>{est}</td><td class=l>{v}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def conditions_table(diag, max_rows: int = 12) -> str:
    eff = sorted(diag.conditions, key=lambda e: e.p_adjusted)[:max_rows]
    rows = ["<tr><th>residuals</th><th>condition</th><th>rank corr.</th><th>p (Holm)</th>"
            "<th>n (effective)</th><th>NIS ratio high/low</th><th>reading</th></tr>"]
    for e in eff:
        rows.append(f"<tr><td class=l>{html.escape(e.series)}</td><td class=l>{e.condition}</td>"
                    f"<td>{e.rho:+.2f}</td><td>{e.p_adjusted:.2g}</td><td>{e.n} ({e.n_eff:.0f})</td>"
                    f"<td>{_fmt(e.ratio, '.2f')}</td><td class=l>{html.escape(e.phrase)}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def params_table(ev) -> str:
    rows = ["<tr><th>parameter</th><th>value</th><th>sigma</th></tr>"]
    for n, v in ev.full.parameters_json().items():
        rows.append(f"<tr><td class=l>{html.escape(n)}</td><td>{v['value']:.5g}</td>"
                    f"<td>{v['sigma']:.2g}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def render(diag, plots: bool = True) -> str:
    """The report as one HTML string."""
    H = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>aqfg diagnosis</title>",
         f"<style>{_CSS}</style></head><body>",
         f"<h1>aqfg diagnosis: {html.escape(', '.join(m.name for m in diag.missions))}</h1>",
         f"<p class=verdict>{html.escape(diag.verdict)}</p>",
         f"<p>{html.escape(diag.confidence_text())}</p>",
         f"<p><b>Where it fails.</b> {html.escape(diag.conditions_text)}</p>"]
    H.append("<h2>Which effect is missing</h2>")
    H.append("<p>Every applicable catalogue effect is scored by a Lagrange-multiplier (score) "
             "test at its null value on the linearised graph of the model fitted to all fixes "
             "(Holm-corrected over the candidates); those with a significant score are "
             "refitted. The missing effect is the one whose score, refit (likelihood ratio, "
             "BIC, direction of the estimate) and held-out fixes (predictive test, "
             "dead-reckoning error) all agree, lowest BIC first; the others are tested again "
             "with it in the model: an <i>echo</i> loses its evidence, <i>independent</i> "
             "evidence stays. An effect is named missing only when its estimate is "
             "plausible (else it 'fits, but is implausible' and names what it probably "
             "absorbs) and the held-out dead-reckoning error beyond the fixes' noise "
             f"({diag.base.noise_floor:.2f} m RMS) falls by at least "
             f"{100 * diag.settings.get('min_gain', MIN_GAIN):.0f}% (else it is 'significant but "
             "negligible'). 'bootstrap first' is how often the effect ranks first when "
             "blocks of time are resampled.</p>")
    H.append(ranking_table(diag))
    if plots:
        H.append(_img(fig_ranking(diag)))
    if diag.before is not None:
        b, a = diag.before, diag.base
        H.append(f"<h2>Added effect(s): {html.escape(', '.join(diag.added))}</h2>")
        H.append("<table><tr><th></th><th>before</th><th>after</th></tr>"
                 f"<tr><td class=l>RMS distance to the held-out fixes (m)</td><td>{b.rmse_raw:.3f}</td>"
                 f"<td>{a.rmse_raw:.3f}</td></tr>"
                 f"<tr><td class=l>their noise floor (m)</td><td>{b.noise_floor:.3f}</td>"
                 f"<td>{a.noise_floor:.3f}</td></tr>"
                 f"<tr><td class=l>DR error beyond the noise (m)</td><td>{_beyond(b)}</td>"
                 f"<td>{_beyond(a)}</td></tr>"
                 f"<tr><td class=l>held-out NIS / expected</td><td>{b.consistency.ratio:.2f}</td>"
                 f"<td>{a.consistency.ratio:.2f}</td></tr>"
                 f"<tr><td class=l>consistency test</td><td>{'pass' if b.consistency.passed else 'FAIL'}</td>"
                 f"<td>{'pass' if a.consistency.passed else 'FAIL'}</td></tr>"
                 f"<tr><td class=l>BIC</td><td>{b.bic:.1f}</td><td>{a.bic:.1f}</td></tr></table>")
        H.append("<h3>Parameters after</h3>" + params_table(a))
    H.append("<h2>Consistency of the model with the held-out fixes</h2>")
    H.append("<p>The model fitted to thinned fixes (GNSS one every "
             f"{diag.settings.get('gnss_every')} s, every other USBL fix) predicts each "
             "held-out fix by dead reckoning from the previous fit fix; the normalised "
             "innovation squared (NIS) should follow chi-square(2). Windows of "
             f"{diag.settings.get('window')} s.</p>")
    if plots:
        H.append(_img(fig_consistency(diag)))
        H.append(_img(fig_growth(diag)))
        for i in range(len(diag.missions)):
            H.append(_img(fig_map(diag, i)))
            H.append(_img(fig_heldout_time(diag, i)))
            H.append(_img(fig_residuals_compare(diag, i)))
    H.append("<h2>Where the model fails</h2>")
    H.append("<p>Spearman rank correlation between the squared normalised residuals and each "
             "condition (averaged over the preceding "
             f"{diag.settings.get('memory')} s), p-values with the effective sample size of "
             "autocorrelated series and Holm's correction.</p>")
    H.append(conditions_table(diag))
    if plots:
        H.append(_img(fig_conditions(diag)))
    H.append("<h2>Model vs measurements</h2>")
    H.append("<h3>Parameters (model fitted to all fixes)</h3>" + params_table(diag.base))
    if plots:
        for i in range(len(diag.missions)):
            H.append(_img(fig_sensors(diag, i)))
    H.append("<h2>Summary</h2><pre>" + html.escape(diag.summary()) + "</pre>")
    H.append("</body></html>")
    return "\n".join(H)


def _write_html(text: str, path) -> Path:
    """Write the page ``text`` to ``path`` (UTF-8); returns the path."""
    p = Path(path)
    p.write_text(text, encoding="utf-8")
    return p


def write_report(diag, path, plots: bool = True) -> Path:
    """Write :func:`render` to ``path``."""
    return _write_html(render(diag, plots=plots), path)


# ---------------------------------------------------------------- the loop (--auto)
def fig_staircase(seq):
    """Held-out dead-reckoning error after each step of a
    :class:`~aqfg.diagnose.sequence.DiagnosisSequence`, labelled with the effect added and
    its estimate; markers filled where the held-out fixes pass the consistency test."""
    plt = _plt()
    st = seq.staircase()
    x = st["step"]
    fig, ax = plt.subplots(figsize=(8, 3.8))
    ax.step(x, st["rmse_raw"], where="post", color="tab:blue", lw=2,
            label="RMS distance to the held-out fixes")
    ax.axhline(seq.bare.noise_floor, color="0.5", ls="--", lw=1,
               label="their noise floor (a perfect prediction)")
    for i in x:
        ok = bool(st["consistent"][i])
        ax.plot(i, st["rmse_raw"][i], "o", ms=8, color="tab:blue",
                mfc="tab:blue" if ok else "white")
        ax.annotate(f"{st['rmse_raw'][i]:.2f} m", (i, st["rmse_raw"][i]),
                    textcoords="offset points", xytext=(6, 6), fontsize=8)
    labels = ["bare model"]
    for s in seq.steps:
        est = "\n".join(f"{n.split('.')[-1]}={v['value']:.3g}±{v['sigma']:.1g}"
                        for n, v in s.estimate.items())
        labels.append(f"+ {s.effect}\n{est}")
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=7)
    ax.set_ylabel("held-out error (m)")
    ax.set_ylim(bottom=0)
    ax.set_title("what each added effect buys (filled: consistent with the held-out fixes)",
                 fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def fig_map_sequence(seq, i: int = 0):
    """Map of mission ``i``: held-out fixes and the model-only legs of the bare and the
    final model."""
    plt = _plt()
    m = seq.missions[i]
    fig, ax = plt.subplots(figsize=(7, 6))
    bare, final = seq.bare, seq.final
    tr = final.full.missions[i].track
    ax.plot(tr.pos[:, 1], tr.pos[:, 0], color="0.7", lw=1, label="fitted track (all fixes)")
    for ev, colour, lab in ((bare, "tab:red", "bare model"),
                            (final, "tab:green", "+ " + " + ".join(seq.added))):
        if not ev.next_fix or (ev is bare and final is bare):
            continue
        for j, leg in enumerate(ev.next_fix[i].legs):
            ax.plot(leg.pos[:, 1], leg.pos[:, 0], color=colour, lw=1,
                    label=f"model only: {lab}" if j == 0 else None)
    h = bare.next_fix[i] if bare.next_fix else None
    if h is not None:
        u = h.used
        ax.scatter(h.fix_ne[u, 1], h.fix_ne[u, 0], s=5, c="k", label="held-out fixes", zorder=3)
    _finish_map(ax, m, "dead reckoning between fit fixes, bare vs final model")
    return fig


def staircase_table(seq) -> str:
    head = ("<tr><th>step</th><th>effect added</th><th>estimate ± sigma</th>"
            "<th>held-out RMS (m)</th><th>noise floor (m)</th><th>DR error beyond the noise (m)</th>"
            "<th>NIS / expected</th>"
            "<th>consistent</th><th>dBIC</th><th>evidence (p: score Holm, LR, held-out)</th>"
            "<th>echoes of it</th></tr>")
    rows = [head]
    b = seq.bare
    rows.append(f"<tr><td>0</td><td class=l>bare model</td><td>–</td><td>{b.rmse_raw:.2f}</td>"
                f"<td>{b.noise_floor:.2f}</td><td>{_beyond(b)}</td>"
                f"<td>{_fmt(b.consistency.ratio, '.2f')}</td>"
                f"<td>{'yes' if b.consistency.passed else 'no'}</td><td>–</td><td>–</td>"
                "<td>–</td></tr>")
    for k, (s, ev) in enumerate(zip(seq.steps, seq.evaluations()[1:]), 1):
        est = "<br>".join(f"{html.escape(n)} = {v['value']:.4g} ± {v['sigma']:.2g}"
                          for n, v in s.estimate.items())
        rows.append(f"<tr><td>{k}</td><td class=l>{html.escape(s.effect)}</td>"
                    f"<td class=l>{est}</td><td>{s.rmse_raw_after:.2f}</td>"
                    f"<td>{ev.noise_floor:.2f}</td><td>{_beyond(ev)}</td>"
                    f"<td>{_fmt(ev.consistency.ratio, '.2f')}</td>"
                    f"<td>{'yes' if s.consistent_after else 'no'}</td><td>{s.bic_change:.1f}</td>"
                    f"<td>{_fmt(s.score_p, '.2g')}, {_fmt(s.lr_p, '.2g')}, "
                    f"{_fmt(s.heldout_p, '.2g')}</td>"
                    f"<td class=l>{html.escape(', '.join(s.echoes)) or '–'}</td></tr>")
    return "<table>" + "".join(rows) + "</table>"


def render_sequence(seq, plots: bool = True) -> str:
    """The report of ``aqfg diagnose --auto`` as one HTML string: the staircase first,
    the before/after figures of the whole sequence, then each step's diagnosis."""
    names = ", ".join(m.name for m in seq.missions)
    H = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>aqfg diagnosis</title>",
         f"<style>{_CSS}</style></head><body>",
         f"<h1>aqfg diagnose --auto: {html.escape(names)}</h1>",
         f"<p class=verdict>{html.escape(seq.verdict())}</p>"]
    if plots:
        H.append(_img(fig_staircase(seq)))
    H.append(staircase_table(seq))
    H.append("<p>Each step diagnoses the model with the effects found so far and adds the "
             "one whose score test, refit (likelihood ratio, BIC, direction of the estimate) "
             "and held-out fixes (paired predictive test, dead-reckoning error) all agree; "
             "it stops when no candidate is confirmed. The held-out fixes are never used by "
             "the fits that predict them (GNSS one every "
             f"{seq.diagnoses[0].settings.get('gnss_every')} s and every other USBL fix are "
             "fitted).</p>")
    H.append("<pre>" + html.escape(seq.summary()) + "</pre>")
    if plots and seq.steps:
        evs = seq.evaluations()
        H.append("<h2>Before and after: the whole sequence</h2>")
        H.append(_img(fig_growth(seq.diagnoses[0], evs)))
        for i in range(len(seq.missions)):
            H.append(_img(fig_map_sequence(seq, i)))
            H.append(_img(fig_heldout_time(seq.diagnoses[0], i, [evs[0], evs[-1]])))
    H.append("<h2>Final model</h2>" + params_table(seq.final))
    for k, d in enumerate(seq.diagnoses, 1):
        H.append(f"<h2>Step {k}: model {html.escape(' + '.join(d.base.effects) or 'bare')}</h2>")
        H.append(f"<p class=verdict>{html.escape(d.verdict)}</p>")
        H.append(f"<p><b>Where it fails.</b> {html.escape(d.conditions_text)}</p>")
        H.append(ranking_table(d))
        if plots:
            H.append(_img(fig_ranking(d)))
    H.append("</body></html>")
    return "\n".join(H)


def write_sequence_report(seq, path, plots: bool = True) -> Path:
    """Write :func:`render_sequence` to ``path``."""
    return _write_html(render_sequence(seq, plots=plots), path)
