"""Structural properties of a linear model: poles, stability, controllability, observability.

Ranks are computed with an orthogonal staircase (block Krylov) iteration rather than the rank
of the Kalman matrix ``[B, AB, ..., A^(n-1) B]``, whose columns span many orders of magnitude
for stiff mechanical models and make the singular-value rank unreliable. Each uncontrollable
or unobservable mode is also identified by the PBH test, which says whether the model is
stabilizable and detectable.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import control as ct
import numpy as np

from pidlab.checks import instance


@dataclass(frozen=True)
class Mode:
    """One eigenvalue of ``A`` with its classification.

    Attributes
    ----------
    value : complex
        Eigenvalue (continuous: rad/s; discrete: z-plane).
    unstable : bool
        ``Re > tol`` (continuous) or ``|z| > 1 + tol`` (discrete).
    marginal : bool
        On the stability boundary within ``tol``.
    controllable, observable : bool
        PBH test: ``rank [A - lambda I, B] == n`` and ``rank [A - lambda I; C] == n``.
    ctrb_margin, obsv_margin : float
        Smallest singular value of those PBH matrices relative to ``max(1, |A|)``: how far
        the mode is from being uncontrollable / unobservable (0 = exactly).
    """

    value: complex
    unstable: bool
    marginal: bool
    controllable: bool
    observable: bool
    ctrb_margin: float
    obsv_margin: float

    @property
    def natural_frequency(self) -> float:
        """``|lambda|`` in rad/s (continuous eigenvalues)."""
        return float(abs(self.value))

    @property
    def damping(self) -> float:
        """Damping ratio ``-Re(lambda) / |lambda|`` (continuous eigenvalues); nan at 0."""
        mag = abs(self.value)
        return float(-self.value.real / mag) if mag > 0 else float("nan")


@dataclass(frozen=True)
class LtiReport:
    """Poles and structural properties of a state-space model.

    Attributes
    ----------
    n : int
        Number of states.
    discrete : bool
        Whether the model is discrete-time.
    dt : float
        Sampling period (0 for continuous time).
    modes : tuple of Mode
        Eigenvalues of ``A``, sorted by real part (continuous) or magnitude (discrete).
    controllable_dim, observable_dim : int
        Dimensions of the controllable and observable subspaces (the ranks of the
        controllability and observability matrices).
    stabilizable, detectable : bool
        No unstable or marginal mode is uncontrollable / unobservable.
    tol : float
        Relative tolerance used for ranks and for the stability boundary.
    """

    n: int
    discrete: bool
    dt: float
    modes: tuple[Mode, ...]
    controllable_dim: int
    observable_dim: int
    stabilizable: bool
    detectable: bool
    tol: float

    @property
    def poles(self) -> np.ndarray:
        """Eigenvalues of ``A``, shape ``(n,)``."""
        return np.array([m.value for m in self.modes])

    @property
    def controllable(self) -> bool:
        """Whether the model is completely controllable."""
        return self.controllable_dim == self.n

    @property
    def observable(self) -> bool:
        """Whether the model is completely observable."""
        return self.observable_dim == self.n

    @property
    def n_unstable(self) -> int:
        """Number of unstable eigenvalues."""
        return sum(m.unstable for m in self.modes)


def reachable_dimension(A: np.ndarray, B: np.ndarray, tol: float = 1e-9) -> int:
    """Dimension of the reachable subspace of ``(A, B)`` by an orthogonal staircase.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    tol : float
        Directions with a singular value below ``tol * max(1, |A|, |B|)`` are dropped.

    Returns
    -------
    int
    """
    if A.shape[0] == 0 or B.size == 0:
        return 0
    return int(_orthonormal_reachable_basis(A, B, tol).shape[1])


def analyze_lti(
    sys: ct.StateSpace, tol: float = 1e-9, progress: Callable[[int, int], None] | None = None
) -> LtiReport:
    """Poles, stability, controllability and observability of ``sys``.

    Parameters
    ----------
    sys : control.StateSpace
        Continuous- or discrete-time model.
    tol : float, default 1e-9
        Relative tolerance for ranks and for classifying poles as marginal.
    progress : callable, optional
        ``progress(done, n)`` after each mode's PBH tests (two SVDs of about ``n x n``
        each: minutes for ``n`` in the hundreds).

    Returns
    -------
    LtiReport
    """
    instance(sys, ct.StateSpace, "sys")
    A, B, C = (np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C))
    n = A.shape[0]
    discrete = bool(sys.isdtime(strict=True))
    eig = np.linalg.eigvals(A) if n else np.zeros(0, dtype=complex)
    scale = max(1.0, float(np.linalg.norm(A, 2))) if n else 1.0
    stab_tol = 1e-7 * scale
    modes = []
    for lam in eig:
        if discrete:
            margin = abs(lam) - 1.0
        else:
            margin = lam.real
        marginal = abs(margin) <= stab_tol
        unstable = margin > stab_tol
        shifted = A - lam * np.eye(n)
        ctrb_margin = _min_singular(np.hstack([shifted, B]), n) / scale
        obsv_margin = _min_singular(np.vstack([shifted, C]), n) / scale
        modes.append(
            Mode(
                complex(lam),
                bool(unstable),
                bool(marginal),
                ctrb_margin > tol,
                obsv_margin > tol,
                ctrb_margin,
                obsv_margin,
            )
        )
        if progress is not None:
            progress(len(modes), n)
    key = (lambda m: abs(m.value)) if discrete else (lambda m: m.value.real)
    modes.sort(key=key)
    return LtiReport(
        n=n,
        discrete=discrete,
        dt=float(sys.dt) if discrete else 0.0,
        modes=tuple(modes),
        controllable_dim=reachable_dimension(A, B, tol),
        observable_dim=reachable_dimension(A.T, C.T, tol),
        stabilizable=all(m.controllable for m in modes if m.unstable or m.marginal),
        detectable=all(m.observable for m in modes if m.unstable or m.marginal),
        tol=tol,
    )


def _min_singular(M: np.ndarray, n: int) -> float:
    """The n-th largest singular value of ``M`` (0 when ``M`` has rank below ``n``)."""
    s = np.linalg.svd(M, compute_uv=False)
    return float(s[n - 1]) if s.size >= n else 0.0


def _orthonormal_reachable_basis(A: np.ndarray, B: np.ndarray, tol: float) -> np.ndarray:
    n = A.shape[0]
    scale = max(1.0, float(np.linalg.norm(A, 2)), float(np.linalg.norm(B, 2)))
    basis = np.zeros((n, 0))
    new = B
    for _ in range(n):
        new = new - basis @ (basis.T @ new)
        u, s, _ = np.linalg.svd(new, full_matrices=False)
        keep = s > tol * scale
        if not np.any(keep):
            break
        q = u[:, keep]
        basis = np.column_stack([basis, q])
        if basis.shape[1] >= n:
            break
        new = A @ q
    return basis[:, :n]


def observable_part(sys: ct.StateSpace, tol: float = 1e-9) -> tuple[ct.StateSpace, tuple[str, ...]]:
    """Restrict ``sys`` to its observable subspace.

    The unobservable subspace is ``A``-invariant and invisible in the outputs, so in an
    orthonormal basis ``V`` of its complement ``(V' A V, V' B, C V, D)`` reproduces every
    input-output behaviour. Used so that modes no output feedback can see (Hopper's and
    Walker2d's ``rootx``) do not count against closed-loop stability.

    Returns
    -------
    reduced : control.StateSpace
        States named ``z0, z1, ...`` unless nothing was removed (then ``sys`` itself).
    removed : tuple of str
        Names of the original states that are (mostly) unobservable, for reporting.
    """
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C, sys.D))
    V = _orthonormal_reachable_basis(A.T, C.T, tol)
    n = A.shape[0]
    if V.shape[1] == n:
        return sys, ()
    # the original state directions least represented in V are the removed ones
    weight = np.sum(V**2, axis=1)
    removed = tuple(sys.state_labels[i] for i in np.argsort(weight)[: n - V.shape[1]])
    reduced = ct.ss(
        V.T @ A @ V,
        V.T @ B,
        C @ V,
        D,
        sys.dt,
        inputs=sys.input_labels,
        outputs=sys.output_labels,
        states=[f"z{i}" for i in range(V.shape[1])],
        name=f"{sys.name}_observable",
    )
    return reduced, removed


def siso_frequency_response(sys: ct.StateSpace, omega: np.ndarray) -> np.ndarray:
    """Frequency response of a SISO state-space model, evaluated in one batched solve.

    ``H = C (zI - A)^-1 B + D`` with ``z = exp(j omega dt)`` (discrete) or ``z = j omega``
    (continuous). Same values as ``sys.frequency_response(omega)`` to rounding, about
    30 times faster on the grids used here (python-control evaluates one frequency at a time).

    Parameters
    ----------
    sys : control.StateSpace
        One input, one output.
    omega : ndarray, shape (m,)
        Frequencies, rad/s.

    Returns
    -------
    response : ndarray of complex, shape (m,)
    """
    A, B, C, D = (np.asarray(M, dtype=float) for M in (sys.A, sys.B, sys.C, sys.D))
    w = np.asarray(omega, dtype=float)
    z = np.exp(1j * w * float(sys.dt)) if sys.isdtime(strict=True) else 1j * w
    n = A.shape[0]
    if n == 0:
        return np.full(w.shape, complex(D[0, 0]))
    M = z[:, None, None] * np.eye(n)[None] - A[None]
    rhs = np.broadcast_to(B[None].astype(complex), (len(w), n, 1))
    with np.errstate(all="ignore"):
        try:
            x = np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError:  # a frequency exactly on a pole: infinite there
            out = np.empty(len(w), dtype=complex)
            for k in range(len(w)):
                try:
                    out[k] = (C @ np.linalg.solve(M[k], rhs[k]))[0, 0] + D[0, 0]
                except np.linalg.LinAlgError:
                    out[k] = complex(np.inf, 0.0)
            return out
    return (C[None] @ x)[:, 0, 0] + D[0, 0]


def siso_disk_margins(L_response: np.ndarray) -> tuple[float, float, float]:
    """Balanced (skew 0) disk margin of a SISO loop from its frequency response.

    For a SISO loop the disk margin at each frequency is ``1 / |S - 1/2|`` with
    ``S = 1 / (1 + L)``; the worst case over the grid gives the disk margin and the gain and
    phase variations it guarantees. Same formulas and values as ``control.disk_margins`` with
    ``skew=0`` on the same grid.

    Returns
    -------
    alpha : float
        Disk margin.
    gain_margin_db : float
    phase_margin_deg : float
    """
    with np.errstate(all="ignore"):
        S = 1.0 / (1.0 + np.asarray(L_response))
        dm = 1.0 / np.abs(S - 0.5)
        g_min = (1 - 0.5 * dm) / (1 + 0.5 * dm)
        g_max = (1 + 0.5 * dm) / (1 - 0.5 * dm)
        dgm = 20 * np.log10(np.minimum(1 / g_min, g_max))
        dgm = np.where(np.isnan(dgm), np.inf, dgm)
        cos_pm = (1 + g_min * g_max) / (g_min + g_max)
        dpm = np.where(np.abs(cos_pm) >= 1.0, np.inf, np.rad2deg(np.arccos(np.clip(cos_pm, -1, 1))))
        dpm = np.where(np.isinf(g_max), 90.0, dpm)
    if dm.size == 0:
        return float("inf"), float("inf"), float("inf")
    gm = float(np.min(dgm)) if not np.isinf(dgm).all() else float("inf")
    return float(np.min(dm)), gm, float(np.min(dpm))
