"""Reproduce every numerical result of Brugnano & Sun (2014) (docs/methods.md#the-papers-numbers).

``reproduce(config_dir, out_dir)`` runs the sweeps ``table1.yaml`` (Tables 1-3 and
Figure 1) and ``long_run.yaml`` (Figures 2-4) from ``configs/paper/`` and writes, in
``out_dir``: one markdown file per table, each value beside the paper's printed value
and the relative difference, and one PNG per figure.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .sweep import RunOutcome, errors_of, load_sweep, orders_of, run_sweep

COLUMNS = ("GAUSS3", "HBVM(12,3)", "EHBVM(12,3) L1", "GHBVM(12,3) L1", "EHBVM(12,3) L1,L2", "GHBVM(12,3) L1,L2")
STEPS = ("pi/30", "pi/60", "pi/120", "pi/240", "pi/480")

# The paper's printed values (Tables 1-3; docs/methods.md#the-papers-numbers lists the first four rows).
TABLE_1 = {
    "pi/30": (1.942e-03, 4.587e-05, 1.017e-05, 4.049e-05, 1.928e-05, 4.367e-05),
    "pi/60": (2.817e-05, 7.375e-07, 1.644e-07, 6.505e-07, 3.052e-07, 6.868e-07),
    "pi/120": (4.346e-07, 1.161e-08, 2.591e-09, 1.023e-08, 4.785e-09, 1.075e-08),
    "pi/240": (6.771e-09, 1.816e-10, 4.030e-11, 1.599e-10, 7.509e-11, 1.677e-10),
    "pi/480": (1.052e-10, 1.815e-12, 4.718e-13, 2.201e-12, 1.413e-12, 2.346e-12),
}
TABLE_2 = {
    "pi/30": (6705, 6775, 7256, 6779, 7474, 6781),
    "pi/60": (11147, 11244, 12691, 11247, 13407, 11249),
    "pi/120": (19085, 19343, 21664, 19339, 23012, 19348),
    "pi/240": (33876, 34752, 37511, 34743, 39117, 34753),
    "pi/480": (61501, 61959, 65125, 61967, 68217, 61970),
}
TABLE_3 = {  # max_n |alpha_n|_inf of EHBVM(12,3): (L1 imposed, L1 and L2 imposed)
    "pi/30": (4.530e-3, 1.246e-2),
    "pi/60": (1.155e-3, 3.195e-3),
    "pi/120": (2.902e-4, 8.040e-4),
    "pi/240": (7.265e-5, 2.013e-4),
    "pi/480": (1.837e-5, 5.055e-5),
}
# Where round-off moves the error by more than the tolerance (0.6-1.7% at pi/240, up to 90% at pi/480:
# bench/results/paper_roundoff.md, in the paper's run too): compared, not held to 2e-3.
ROUND_OFF_ROWS = ("pi/240", "pi/480")
TOLERANCE = 2e-3


def _relative(value: float, paper: float) -> float:
    return value / paper - 1.0


def table_1(spec, outcomes):
    """Rows (h, column, elimfast error, paper error, relative difference, order)."""
    errors = errors_of(spec, outcomes, None)
    orders = orders_of(spec, outcomes, errors)
    by_key = {(o.coordinates["method"], o.coordinates["h"]): o for o in outcomes}
    rows = []
    for h in STEPS:
        for column, paper in zip(COLUMNS, TABLE_1[h]):
            outcome = by_key[(column, h)]
            value = errors[outcome.label]
            rows.append((h, column, value, paper, _relative(value, paper), orders[outcome.label]))
    return rows


def table_2(outcomes):
    by_key = {(o.coordinates["method"], o.coordinates["h"]): o for o in outcomes}
    return [(h, column, by_key[(column, h)].iterations_total, paper)
            for h in STEPS for column, paper in zip(COLUMNS, TABLE_2[h])]


def table_3(outcomes):
    by_key = {(o.coordinates["method"], o.coordinates["h"]): o for o in outcomes}
    rows = []
    for h in STEPS:
        for column, paper in zip(("EHBVM(12,3) L1", "EHBVM(12,3) L1,L2"), TABLE_3[h]):
            value = by_key[(column, h)].max_multiplier
            rows.append((h, column, value, paper, _relative(value, paper)))
    return rows


def _markdown_table_1(rows) -> str:
    lines = ["# Table 1: max-norm error of y(20 pi) - y0, Kepler e = 0.6", "",
             f"Relative difference to the paper; at {', '.join(ROUND_OFF_ROWS)} round-off (the paper's and "
             "elimfast's) moves the errors by more than the tolerance (docs/methods.md#the-papers-numbers): those rows "
             "are shown for comparison only.", "",
             "| h | method | elimfast | paper | rel. diff | order |", "|---|---|---|---|---|---|"]
    for h, column, value, paper, rel, order in rows:
        flag = "" if h in ROUND_OFF_ROWS or abs(rel) < TOLERANCE else " **(!)**"
        order_text = "" if math.isnan(order) else f"{order:.2f}"
        lines.append(f"| {h} | {column} | {value:.4e} | {paper:.3e} | {rel:+.2e}{flag} | {order_text} |")
    return "\n".join(lines) + "\n"


def _markdown_table_2(rows) -> str:
    lines = ["# Table 2: total fixed-point iterations", "",
             "They depend on the stopping rule (docs/methods.md#the-papers-numbers): elimfast stops at round-off, "
             "starts each step from the previous step's coefficients and uses the stable right-hand side "
             "(docs/methods.md#stable-right-hand-side), with which EHBVM "
             "needs about as many iterations as HBVM.", "",
             "| h | method | elimfast | paper | ratio |", "|---|---|---|---|---|"]
    for h, column, value, paper in rows:
        lines.append(f"| {h} | {column} | {value} | {paper} | {value / paper:.3f} |")
    return "\n".join(lines) + "\n"


def _markdown_table_3(rows) -> str:
    lines = ["# Table 3: max |alpha|_inf of EHBVM(12,3)", "",
             "| h | imposed | elimfast | paper | rel. diff |", "|---|---|---|---|---|"]
    for h, column, value, paper, rel in rows:
        flag = "" if h in ROUND_OFF_ROWS or abs(rel) < TOLERANCE else " **(!)**"
        lines.append(f"| {h} | {column.split()[-1]} | {value:.4e} | {paper:.3e} | {rel:+.2e}{flag} |")
    return "\n".join(lines) + "\n"


def _figures(table_outcomes: list[RunOutcome], long_outcomes: list[RunOutcome], out_dir: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    by_label = {o.coordinates["method"]: o for o in long_outcomes}

    def save(fig, name):
        path = out_dir / name
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    # Figure 1: the two alpha components, EHBVM(12,3) imposing L1 and L2, h = pi/30.
    outcome = next(o for o in table_outcomes if o.coordinates == {"method": "EHBVM(12,3) L1,L2", "h": "pi/30"})
    alpha = outcome.result.alpha
    t = outcome.h * np.arange(1, alpha.shape[0] + 1)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i in range(alpha.shape[1]):
        ax.plot(t, alpha[:, i], lw=1, label=f"alpha_{i + 1}")
    ax.set(xlabel="t", ylabel="alpha", title="Figure 1: components of alpha, EHBVM(12,3) imposing L1, L2, h = pi/30")
    ax.legend()
    save(fig, FIGURES[0])

    def invariant_error(o, name):
        values = o.result.invariants[name]
        return o.result.t, np.abs(values - o.result.initial_invariants()[name])   # against I(t0)

    for number, label, name, title in ((2, "GAUSS3", "H", "Hamiltonian error, GAUSS3"),
                                       (3, "HBVM(12,3)", "angular_momentum", "angular momentum error, HBVM(12,3)")):
        t, err = invariant_error(by_label[label], name)
        fig, ax = plt.subplots(figsize=(8, 4.5))
        ax.semilogy(t[1:], np.maximum(err[1:], 1e-17), lw=0.8)
        ax.set(xlabel="t", ylabel="error", title=f"Figure {number}: {title}, h = 0.1")
        save(fig, FIGURES[number - 1])

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label in COLUMNS:
        t, ex = invariant_error(by_label[label], "lrl_x")
        _, ey = invariant_error(by_label[label], "lrl_y")
        ax.semilogy(t[1:], np.maximum(np.hypot(ex, ey)[1:], 1e-17), lw=0.8, label=label)
    ax.set(xlabel="t", ylabel="|A(t) - A(0)|", title="Figure 4: error in the LRL vector, h = 0.1")
    ax.legend(fontsize=8)
    save(fig, FIGURES[3])
    return written


def drift_summary(long_outcomes: list[RunOutcome]) -> dict[str, dict[str, float]]:
    """For each method and H, L1, |A|: the max error over the first and the last tenth of the run."""
    summary = {}
    for o in long_outcomes:
        names = list(o.result.invariants)
        inv = np.column_stack([o.result.invariants[name] for name in names])
        n = inv.shape[0]
        tenth = max(1, n // 10)
        entry = {}
        for key, columns in (("H", ["H"]), ("angular_momentum", ["angular_momentum"]), ("lrl", ["lrl_x", "lrl_y"])):
            err = np.sqrt(sum((inv[:, names.index(c)] - inv[0, names.index(c)]) ** 2 for c in columns))
            entry[key] = (float(err[:tenth].max()), float(err[-tenth:].max()))
        summary[o.coordinates["method"]] = entry
    return summary


def _markdown_long_run(summary) -> str:
    lines = ["# Long run, h = 0.1 on [0, 1000] (Figures 2-4)", "",
             "Max invariant error over the first and the last tenth of the run: a bounded error keeps about "
             "the same size, a drift grows.", "",
             "| method | H first | H last | L1 first | L1 last | LRL first | LRL last |", "|---|---|---|---|---|---|---|"]
    for method, entry in summary.items():
        cells = [f"{entry[k][i]:.2e}" for k in ("H", "angular_momentum", "lrl") for i in (0, 1)]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# What reproduce writes into its folder (elimfast paper refuses to replace them without --overwrite).
TABLES = ("table1.md", "table2.md", "table3.md", "long_run.md")
FIGURES = ("figure1_alpha.png", "figure2_gauss3_H.png", "figure3_hbvm_angular_momentum.png", "figure4_lrl.png")


def reproduce(config_dir: str | Path, out_dir: str | Path, workers: int | None = None, on_done=None) -> dict:
    """Run both paper sweeps and write the tables and figures. Returns the computed rows."""
    config_dir, out_dir = Path(config_dir), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    table_spec = load_sweep(config_dir / "table1.yaml")
    long_spec = load_sweep(config_dir / "long_run.yaml")
    table_outcomes, _ = run_sweep(table_spec, workers=workers, on_done=on_done)
    long_outcomes, _ = run_sweep(long_spec, workers=workers, on_done=on_done)
    failed = [o for o in table_outcomes + long_outcomes if not o.ok]
    if failed:
        raise RuntimeError("; ".join(f"{o.label}: {o.status}" for o in failed))
    rows1, rows2, rows3 = table_1(table_spec, table_outcomes), table_2(table_outcomes), table_3(table_outcomes)
    summary = drift_summary(long_outcomes)
    for name, text in zip(TABLES, (_markdown_table_1(rows1), _markdown_table_2(rows2), _markdown_table_3(rows3),
                                   _markdown_long_run(summary))):
        (out_dir / name).write_text(text)
    figures = _figures(table_outcomes, long_outcomes, out_dir)
    return {"table1": rows1, "table2": rows2, "table3": rows3, "long_run": summary, "figures": figures,
            "outcomes": (table_outcomes, long_outcomes)}
