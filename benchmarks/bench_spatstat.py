"""Point processes side by side with R's spatstat: sites sampled from a Thomas process (about
100,000) and from a Strauss process (about 10,000: the most spatstat's samplers reach in
minutes), and each model fitted to such a pattern, on the same model and window.

* Thomas: kappa 0.01 parents/m², 10 trees each, scale 3 m, on 1,000 m x 1,000 m. usdforest
  ``clusters.simulate`` against ``rThomas``; the fit by minimum contrast on K (q = 1/4, r up
  to 15 m: the translation-corrected K of ``sites.pattern`` and the contrast of
  ``sites.fit``) against ``kppm(X ~ 1, "Thomas", rmax = 15)``.
* Strauss: beta 0.12, radius 2 m, gamma 0.3, on 400 m x 400 m and, for usdforest alone,
  on 1,200 m x 1,200 m (about 93,000 sites). usdforest ``inhibition.simulate``
  (birth-death Metropolis-Hastings, 50 steps a tree) against ``rmh`` with the same number
  of steps and against ``rStrauss`` (dominated coupling from the past: exact); the fit at
  the known radius by logistic composite likelihood with the border correction
  (``sites.fit.fit_strauss``) against ``ppm(X ~ 1, Strauss(2), method = "logi")``, each on
  its own sample.

Each operation's best of three in one process (spatstat's Strauss samplers: one run;
usdforest after a warm-up that compiles its numba code; R after loading its packages). The
ratio is spatstat's time over usdforest's: 1 or
more is at least as fast. Where ``Rscript`` or the packages (Debian: r-cran-spatstat.random,
r-cran-spatstat.model) are absent, spatstat's rows say so and the rest still runs.

Usage: ``python benchmarks/bench_spatstat.py`` (``make bench`` runs it).
"""

from __future__ import annotations

import math
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

THOMAS = {"kappa": 0.01, "mu": 10.0, "scale": 3.0, "side": 1000.0, "rmax": 15.0}
STRAUSS = {"beta": 0.12, "gamma": 0.3, "r": 2.0, "side": 400.0, "big": 1200.0}
R_LIMIT = 900  # seconds for the whole R script

# one "key value" line per figure, so a script stopped at its limit still reports the rest
R_SCRIPT = r"""
suppressMessages({library(spatstat.random); library(spatstat.model)})
best <- function(f, k = 3) min(sapply(1:k, function(i) system.time(f())[["elapsed"]]))
say <- function(key, value) cat(key, value, "\n")
w1 <- owin(c(0, %(t_side)s), c(0, %(t_side)s))
w2 <- owin(c(0, %(s_side)s), c(0, %(s_side)s))
set.seed(1)
say("thomas_sample", best(function() X <<- rThomas(kappa = %(kappa)s, scale = %(scale)s,
    mu = %(mu)s, win = w1)))
say("thomas_n", npoints(X))
say("thomas_fit", best(function() FT <<- kppm(X ~ 1, "Thomas", rmax = %(rmax)s)))
say("thomas_scale", FT$clustpar[["scale"]])
n0 <- %(beta)s * %(s_side)s^2
model <- list(cif = "strauss", par = list(beta = %(beta)s, gamma = %(gamma)s, r = %(r)s), w = w2)
say("strauss_mh", best(function() Z <<- rmh(model, start = list(n.start = n0),
    control = list(nrep = 50 * n0), verbose = FALSE), 1))
say("strauss_mh_n", npoints(Z))
say("strauss_fit", best(function() GS <<- ppm(Z ~ 1, Strauss(%(r)s), method = "logi")))
say("strauss_gamma", exp(coef(GS)[["Interaction"]]))
say("strauss_sample", best(function() Y <<- rStrauss(beta = %(beta)s, gamma = %(gamma)s,
    R = %(r)s, W = w2), 1))
say("strauss_n", npoints(Y))
"""


def _best(f, n: int = 3) -> tuple[float, object]:
    out, best = None, math.inf
    for _ in range(n):
        t = time.perf_counter()
        out = f()
        best = min(best, time.perf_counter() - t)
    return best, out


def ours() -> dict:
    from usdforest.seeds import stream
    from usdforest.sites.clusters import Clusters, simulate
    from usdforest.sites.fit import _thomas_contrast, fit_strauss
    from usdforest.sites.inhibition import Inhibition
    from usdforest.sites.inhibition import simulate as strauss
    from usdforest.sites.pattern import k_function
    from usdforest.sites.pointprocess import Constant, Rectangle

    t, s = THOMAS, STRAUSS
    box1 = (0.0, 0.0, t["side"], t["side"])
    c = Clusters("thomas", t["scale"], t["mu"])
    rng = np.random.default_rng(1)
    out = {}
    out["thomas_sample"], x = _best(lambda: simulate(c, t["kappa"], box1, rng))
    r = np.linspace(t["rmax"] / 60, t["rmax"], 60)
    out["thomas_fit"], fitted = _best(lambda: _thomas_contrast(k_function(x, box1, r), r))
    out["thomas_n"], out["thomas_scale"] = len(x), fitted[1]
    model, beta = Inhibition("strauss", s["r"], s["gamma"]), Constant(s["beta"])
    strauss(model, Rectangle(0, 0, 50, 50), beta, stream(0, "warm"))  # compile numba's code
    radius = np.array([s["r"]])
    for tag, side in (("", s["side"]), ("big_", s["big"])):
        box = (0.0, 0.0, side, side)
        out[f"{tag}strauss_sample"], y = _best(
            lambda box=box: strauss(model, Rectangle(*box), beta, stream(1, "bench"))
        )
        out[f"{tag}strauss_fit"], g = _best(
            lambda y=y, box=box: fit_strauss(y, box, False, radius, s["r"])
        )
        out[f"{tag}strauss_n"], out[f"{tag}strauss_gamma"] = len(y), g[1]
    out["strauss_mh"], out["strauss_mh_n"] = out["strauss_sample"], out["strauss_n"]
    return out


def spatstat() -> dict | str:
    """spatstat's figures (those it reached within ``R_LIMIT``), or why there are none."""
    exe = shutil.which("Rscript")
    if exe is None:
        return "Rscript not found (Debian: r-cran-spatstat.random r-cran-spatstat.model)"
    code = R_SCRIPT % {**THOMAS, **STRAUSS, "t_side": THOMAS["side"], "s_side": STRAUSS["side"]}
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "bench.R"
        script.write_text(code)
        try:
            r = subprocess.run([exe, str(script)], capture_output=True, text=True,
                               timeout=R_LIMIT)  # fmt: skip
            text, err = r.stdout, r.stderr if r.returncode else ""
        except subprocess.TimeoutExpired as exc:
            text, err = (exc.stdout or b"").decode(), ""
    got = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 2:
            got[parts[0]] = float(parts[1])
    if not got:
        return f"spatstat did not run: {err.strip().splitlines()[-1] if err.strip() else ''}"
    return got


def main() -> None:
    a, b = ours(), spatstat()
    print("| operation | usdforest | spatstat | spatstat / usdforest |")
    print("| --- | --- | --- | --- |")
    n = f"{STRAUSS['side'] ** 2 * STRAUSS['beta']:,.0f}"
    rows = (
        ("Thomas: sample (rThomas)", "thomas_sample", "thomas_n", "sites"),
        ("Thomas: fit by minimum contrast on K (kppm)", "thomas_fit", "thomas_scale", "m scale"),
        ("Strauss: sample, Metropolis-Hastings, 50 steps a tree (rmh)", "strauss_mh",
         "strauss_mh_n", "sites"),
        ("Strauss: sample, exact (rStrauss: coupling from the past)", "strauss_sample",
         "strauss_n", "sites"),
        ("Strauss: fit, logistic composite likelihood (ppm, logi)", "strauss_fit",
         "strauss_gamma", "gamma"),
        ("Strauss, 1,200 m square: sample", "big_strauss_sample", "big_strauss_n", "sites"),
        ("Strauss, 1,200 m square: fit", "big_strauss_fit", "big_strauss_gamma", "gamma"),
    )  # fmt: skip
    for name, key, what, unit in rows:
        mine = f"{a[key]:.2f} s ({a[what]:,.4g} {unit})"
        if isinstance(b, str):
            print(f"| {name} | {mine} | {b} | - |")
        elif key.startswith("big_"):
            print(f"| {name} | {mine} | not run: rStrauss grows faster than n² | - |")
        elif key not in b:
            print(f"| {name} | {mine} | not reached within the script's {R_LIMIT} s | - |")
        else:
            print(f"| {name} | {mine} | {b[key]:.2f} s ({b[what]:,.4g} {unit}) | "
                  f"{b[key] / a[key]:.2f}x |", flush=True)  # fmt: skip
    print(f"\nStrauss rows: beta {STRAUSS['beta']}, r {STRAUSS['r']} m, gamma "
          f"{STRAUSS['gamma']} on a {STRAUSS['side']:g} m square (beta x area = {n}) unless "
          "named; usdforest's sample is its Metropolis-Hastings chain in both rows.")  # fmt: skip


if __name__ == "__main__":
    main()
