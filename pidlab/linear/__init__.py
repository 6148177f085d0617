"""Stage 1, linearization: linear models of a MuJoCo model about an operating point.

- :mod:`pidlab.linear.linearize` differentiates ``mj_forward`` (RK4 models included) into
  python-control state-space models, continuous and discrete;
- :mod:`pidlab.linear.lti` reports eigenvalues, controllability and observability;
- :mod:`pidlab.linear.symbolic` builds CasADi expressions for the Lyapunov analysis;
- :mod:`pidlab.linear.validate` compares the linear prediction with MuJoCo.
"""
