"""nlopt L-BFGS that keeps the best point it has seen."""

import numpy as np

from doe import interrupts


def minimise(fun, x0, max_eval, ftol_rel=1e-10):
    """Minimise ``fun(x) -> (value, grad)`` with nlopt L-BFGS; return (best x, best value).

    nlopt wants the gradient written in place and drops its best point on some
    exceptions (a round-off stop, an error raised in ``fun``), so the best point
    is tracked here.
    """
    import nlopt

    best = {"x": x0.copy(), "f": np.inf}
    interrupted = []

    def f(x, grad):
        try:
            value, g = fun(x)
        except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM: nlopt would end as if converged
            interrupted.append(e)
            opt.force_stop()
            return float("inf")
        if grad.size:
            grad[:] = g.ravel()
        if value < best["f"]:
            best["f"], best["x"] = value, x.copy()
        return value

    opt = nlopt.opt(nlopt.LD_LBFGS, x0.size)
    opt.set_min_objective(f)
    opt.set_maxeval(int(max_eval))
    opt.set_ftol_rel(ftol_rel)
    # nlopt >= 2.11 raises a generic failure (e.g. a line search that finds no
    # descent) as its own nlopt.runtime_error, a subclass of nlopt.exception, not
    # as Python's RuntimeError
    stops = (
        nlopt.RoundoffLimited,
        nlopt.ForcedStop,
        ValueError,
        RuntimeError,
        getattr(nlopt, "exception", RuntimeError),
    )
    try:
        opt.optimize(x0.ravel().copy())
    except stops:
        pass  # keep our own best point: nlopt drops it on these exceptions
    if interrupted:
        raise interrupted[0]
    # A signal at the edge of f, outside its try, reaches nlopt, which ends with
    # ForcedStop as if converged; the command line has still recorded it.
    interrupts.check()
    return best["x"], best["f"]
