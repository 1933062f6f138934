"""Derivation throughput (modules/s) and turtle throughput (segments/s)."""

from __future__ import annotations

from usdforest.grow.lsystem import derive, make_lsystem
from usdforest.grow.species import get_species, grow
from usdforest.grow.turtle import TurtleConfig, interpret

ALGAE = make_lsystem("b", ["a -> ab", "b -> a"])
PLANT = make_lsystem("X", ["X -> F[+X][-X]FX", "F -> FF"])
STOCHASTIC = make_lsystem("F", ["F -(1/3)-> F[+F]F[-F]F", "F -(1/3)-> F[+F]F", "F -(1/3)-> F[-F]F"])
PARAMETRIC = make_lsystem(
    "A(1,0)", ["A(l,w) -> F(l)[+(uniform(20,40))A(l*0.8,w+1)][-(uniform(20,40))A(l*0.8,w+1)]"]
)
PLANT_WORD = derive(PLANT, 10).word


def derive_algae() -> tuple[int, str]:
    return len(derive(ALGAE, 30).word), "modules"  # 1.35 M


def derive_bracketed() -> tuple[int, str]:
    return len(derive(PLANT, 10).word), "modules"  # ABOP 1.24e at n=10


def derive_stochastic() -> tuple[int, str]:
    return len(derive(STOCHASTIC, 10, seed=1).word), "modules"


def derive_parametric() -> tuple[int, str]:
    return len(derive(PARAMETRIC, 17, seed=1).word), "modules"


def turtle_plant() -> tuple[int, str]:
    return interpret(PLANT_WORD, TurtleConfig(angle=25.7)).n_segments, "segments"


def grow_pine() -> tuple[int, str]:
    return grow(get_species("pine"), seed=1).skeleton.n_segments, "segments"


BENCHMARKS = {
    "derive: algae n=30": derive_algae,
    "derive: bracketed plant (ABOP 1.24e) n=10": derive_bracketed,
    "derive: stochastic plant (ABOP 1.27) n=10": derive_stochastic,
    "derive: parametric, random angles n=17": derive_parametric,
    "turtle: ABOP 1.24e n=10": turtle_plant,
    "grow: pine preset (derive + turtle)": grow_pine,
}
