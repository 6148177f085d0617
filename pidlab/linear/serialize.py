"""JSON-ready descriptions of a linearization (what ``pidlab linearize --json`` prints)."""

from __future__ import annotations

from typing import Any

import numpy as np

from pidlab.linear.linearize import Linearization
from pidlab.linear.lti import LtiReport


def _complex_list(values: np.ndarray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in values]


def linearization_to_dict(lin: Linearization, report_c: LtiReport, report_d: LtiReport) -> dict[str, Any]:
    """A JSON-ready description of a linearization and both structural reports."""

    def rep(r: LtiReport) -> dict[str, Any]:
        return {
            "eigenvalues": _complex_list(r.poles),
            "unstable": [m.unstable for m in r.modes],
            "controllable_modes": [m.controllable for m in r.modes],
            "observable_modes": [m.observable for m in r.modes],
            "controllability_rank": r.controllable_dim,
            "observability_rank": r.observable_dim,
            "n": r.n,
            "stabilizable": r.stabilizable,
            "detectable": r.detectable,
        }

    return {
        "source": lin.source,
        "states": list(lin.state_names),
        "inputs": list(lin.input_names),
        "outputs": list(lin.output_names),
        "operating_point": lin.op.to_dict(),
        "eps": lin.eps,
        "centered": lin.centered,
        "method": lin.method,
        "discretization": lin.discretization,
        "integrator": lin.integrator,
        "timestep": lin.timestep,
        "frame_skip": lin.frame_skip,
        "control_dt": lin.control_dt,
        "equilibrium_error": lin.equilibrium_error,
        "xdot0": lin.xdot0.tolist(),
        "contacts": lin.ncon,
        "constraint_rows": lin.nefc,
        "kink": lin.kink,
        "continuous": {
            "A": lin.A.tolist(),
            "B": lin.B.tolist(),
            "C": lin.C.tolist(),
            "D": lin.D.tolist(),
            **rep(report_c),
        },
        "discrete": {
            "dt": lin.control_dt,
            "A": lin.Ad.tolist(),
            "B": lin.Bd.tolist(),
            "C": np.asarray(lin.sysd.C).tolist(),
            "D": np.asarray(lin.sysd.D).tolist(),
            **rep(report_d),
        },
    }
