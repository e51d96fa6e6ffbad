"""nlopt L-BFGS that keeps the best point it has seen."""

import numpy as np

from doe.infra import interrupts


def minimise(fun, x0, max_eval, ftol_rel=1e-10):
    """Minimise ``fun(x) -> (value, grad)`` with nlopt L-BFGS; return (best x, best value).

    nlopt wants the gradient written in place and drops its best point on some
    exceptions (a round-off stop, a failed line search), so the best point is
    tracked here. An error raised in ``fun`` (or Ctrl-C) stops the search and is
    raised again: nlopt would otherwise end as if it had converged.
    """
    import nlopt

    x0 = np.asarray(x0, dtype=np.float64)
    if not np.all(np.isfinite(x0)):
        raise ValueError("the start point holds a NaN or an infinity")
    if int(max_eval) < 1:  # nlopt reads 0 as "no limit"
        raise ValueError(f"max_eval must be at least 1, got {max_eval}")
    best = {"x": x0.ravel().copy(), "f": np.inf}
    raised = []

    def f(x, grad):
        if raised:  # nlopt may call once more after force_stop
            return float("inf")
        try:
            value, g = fun(x.reshape(x0.shape))
            if grad.size:
                grad[:] = np.ravel(g)
        except BaseException as e:  # kept, and raised again once nlopt has stopped
            raised.append(e)
            opt.force_stop()
            return float("inf")
        if value < best["f"]:
            best["f"], best["x"] = value, x.copy()
        return value

    opt = nlopt.opt(nlopt.LD_LBFGS, x0.size)
    opt.set_min_objective(f)
    opt.set_maxeval(int(max_eval))
    opt.set_ftol_rel(ftol_rel)
    # nlopt >= 2.11 raises a generic failure (e.g. a line search that finds no
    # descent) as its own nlopt.runtime_error, a subclass of nlopt.exception; older
    # versions as Python's RuntimeError. Errors of fun never reach nlopt (see f).
    stops = (
        nlopt.RoundoffLimited,
        nlopt.ForcedStop,
        RuntimeError,
        getattr(nlopt, "exception", RuntimeError),
    )
    try:
        opt.optimize(x0.ravel().copy())
    except stops:
        pass  # keep our own best point: nlopt drops it on these exceptions
    if raised:
        raise raised[0]
    # A signal at the edge of f, outside its try, reaches nlopt, which ends with
    # ForcedStop as if converged; the command line has still recorded it.
    interrupts.check()
    return best["x"].reshape(x0.shape), best["f"]
