"""Research tools on top of the controller (docs/method.md §9): scenarios and the hands-on simulation,
metrics, studies and their parallel runner, benchmarks (tick, QP solvers), the fuzz test, plots."""
