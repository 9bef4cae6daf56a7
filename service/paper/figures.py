"""The report's figures: matplotlib (Agg, no display), each returned as PNG bytes.

Each function redraws one of the paper's figures from what service/paper/experiments.py measured;
amplitudes of alpha are in sensor full scale (FS), as the paper normalises them (Fig. 8-10).
"""

from __future__ import annotations

import io
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)
import numpy as np  # noqa: E402

from service.paper.scope import Trace  # noqa: E402

DPI = 90
COLORS = {"without": "#888888", "with": "#1f77b4", "coupled": "#d62728", "decoupled": "#2ca02c"}


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    return buf.getvalue()


def grid_maps(grid_rows: list, minimum: dict, fit: dict, paper: dict) -> bytes:
    """Fig. 8: amplitude and phase of the 6th harmonic of alpha over (gamma, delta)."""
    g = np.asarray(grid_rows, dtype=float)  # gamma_deg, delta_deg, a_c, a_s
    gammas, deltas = np.unique(g[:, 0]), np.unique(g[:, 1])
    amp = np.full((len(gammas), len(deltas)), np.nan)
    phase = np.full_like(amp, np.nan)
    for gd, dd, a_c, a_s in g:
        i, j = np.searchsorted(gammas, gd), np.searchsorted(deltas, dd)
        amp[i, j] = math.hypot(a_c, a_s)
        phase[i, j] = math.degrees(math.atan2(-a_s, a_c))  # angle of A = a_c - j a_s (docs/conventions.md, Phasors)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, data, title, cmap in (
        (axes[0], amp, "amplitude of the 6th harmonic of alpha (FS)", "viridis"),
        (axes[1], phase, "phase of the 6th harmonic of alpha (deg)", "twilight"),
    ):
        mesh = ax.pcolormesh(deltas, gammas, data, shading="nearest", cmap=cmap)
        fig.colorbar(mesh, ax=ax)
        ax.scatter(g[:, 1], g[:, 0], s=2, c="k", alpha=0.3)
        ax.plot(minimum["delta_deg"], minimum["gamma_deg"], "wo", mec="k", ms=9, label="grid minimum")
        ax.plot(fit["delta_deg"], fit["gamma_deg"], "r+", ms=14, mew=2, label="affine fit")
        ax.plot(paper["delta_deg"], paper["gamma_deg"], "x", color="orange", ms=10, mew=2, label="paper")
        ax.set_xlabel("delta (deg)")
        ax.set_ylabel("gamma (deg)")
        ax.set_title(title, fontsize=10)
    axes[0].legend(loc="upper right", fontsize=8)
    return _png(fig)


def adaptive_transient(history: np.ndarray, paper_theta: tuple[float, float] | None, title: str) -> bytes:
    """Fig. 9: residual amplitude of alpha and the filter states theta over plant time."""
    t, tc, ts, amp = history.T
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    axes[0].semilogy(t, amp, "o-", ms=3)
    axes[0].axhline(amp[0] / 100, color="k", ls=":", lw=1, label="40 dB below theta = 0")
    axes[0].set_xlabel("plant time (s)")
    axes[0].set_ylabel("|6th harmonic of alpha| (FS)")
    axes[0].legend(fontsize=8)
    axes[1].step(t, np.degrees(tc), where="post", label="theta_cos")
    axes[1].step(t, np.degrees(ts), where="post", label="theta_sin")
    if paper_theta is not None:
        for value, name in zip(paper_theta, ("cos", "sin")):
            axes[1].axhline(math.degrees(value), ls="--", lw=1, color="gray")
        axes[1].text(t[-1], math.degrees(paper_theta[0]), " paper", va="bottom", ha="right", fontsize=8, color="gray")
    axes[1].set_xlabel("plant time (s)")
    axes[1].set_ylabel("theta (deg)")
    axes[1].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _png(fig)


def _trajectory(ax, traces: dict[str, Trace], u_limit_v: float | None) -> None:
    for label, tr in traces.items():
        ax.plot(tr["u_d_star_v"], tr["u_q_star_v"], lw=0.8, color=COLORS.get(label), label=label)
    if u_limit_v:
        phi = np.linspace(0, 2 * math.pi, 400)
        ax.plot(u_limit_v * np.cos(phi), u_limit_v * np.sin(phi), "k:", lw=0.8, label="U_dc/sqrt(3)")
    all_d = np.concatenate([tr["u_d_star_v"] for tr in traces.values()])
    all_q = np.concatenate([tr["u_q_star_v"] for tr in traces.values()])
    pad = 0.15 * max(np.ptp(all_d), np.ptp(all_q), 0.05)
    ax.set_xlim(all_d.min() - pad, all_d.max() + pad)
    ax.set_ylim(all_q.min() - pad, all_q.max() + pad)
    ax.set_xlabel("u_d* (V)")
    ax.set_ylabel("u_q* (V)")
    ax.legend(fontsize=8)


def op2_comparison(traces: dict[str, Trace], spectra: dict[str, list], u_limit_v: float) -> bytes:
    """Fig. 10: u_dq* trajectory, i_dq over time, alpha order spectrum; without / with compensation."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.9))
    _trajectory(axes[0], traces, u_limit_v)
    axes[0].set_title("u_dq* (scope)", fontsize=10)
    for label, tr in traces.items():
        n = min(len(tr.time_s), 400)
        axes[1].plot(
            tr.time_s[:n] * 1e3, tr["i_d_a"][:n], color=COLORS.get(label), ls="--", lw=0.8, label=f"i_d {label}"
        )
        axes[1].plot(tr.time_s[:n] * 1e3, tr["i_q_a"][:n], color=COLORS.get(label), lw=0.8, label=f"i_q {label}")
    axes[1].set_xlabel("time (ms)")
    axes[1].set_ylabel("current (A)")
    axes[1].set_title("i_dq (scope)", fontsize=10)
    axes[1].legend(fontsize=7)
    width = 0.4
    for k, (label, spectrum) in enumerate(spectra.items()):
        orders = np.arange(1, len(spectrum) + 1)
        axes[2].bar(orders + (k - 0.5) * width, spectrum, width=width, color=COLORS.get(label), label=label)
    axes[2].set_yscale("log")
    axes[2].set_xlabel("electrical order")
    axes[2].set_ylabel("|alpha| (FS)")
    axes[2].set_title("alpha spectrum (service DAQ)", fontsize=10)
    axes[2].legend(fontsize=8)
    return _png(fig)


def sim_comparison(
    histories: dict[str, np.ndarray], traces: dict[str, Trace], gamma_max_deg: float | None, title: str
) -> bytes:
    """Fig. 11 / 12: the adaptive transient with and without decoupling, |u_dq*| and i_dq in steady state."""
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.8))
    for label, rows in histories.items():
        axes[0].semilogy(rows[:, 0], rows[:, 3], "o-", ms=2, color=COLORS.get(label), label=label)
        axes[1].plot(
            rows[:, 0], np.degrees(np.hypot(rows[:, 1], rows[:, 2])), "o-", ms=2, color=COLORS.get(label), label=label
        )
    axes[0].set_xlabel("plant time (s)")
    axes[0].set_ylabel("|6th harmonic of alpha| (FS)")
    axes[0].legend(fontsize=8)
    if gamma_max_deg:
        axes[1].axhline(gamma_max_deg, color="k", ls=":", lw=1, label="gamma_max")
    axes[1].set_xlabel("plant time (s)")
    axes[1].set_ylabel("gamma (deg)")
    axes[1].legend(fontsize=8)
    for label, tr in traces.items():
        axes[2].plot(tr.time_s * 1e3, tr.u_star_magnitude_v, color=COLORS.get(label), lw=0.8, label=label)
        axes[3].plot(tr.time_s * 1e3, tr["i_d_a"], color=COLORS.get(label), ls="--", lw=0.8, label=f"i_d {label}")
        axes[3].plot(tr.time_s * 1e3, tr["i_q_a"], color=COLORS.get(label), lw=0.8, label=f"i_q {label}")
    axes[2].set_xlabel("time (ms)")
    axes[2].set_ylabel("|u_dq*| (V), scope")
    axes[2].legend(fontsize=8)
    axes[3].set_xlabel("time (ms)")
    axes[3].set_ylabel("current (A), scope")
    axes[3].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    return _png(fig)
