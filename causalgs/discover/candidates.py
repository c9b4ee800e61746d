"""The catalogue of effects discovery may add: each a few bounded parameters of a registered simulator effect.

A :class:`Candidate` says which term it adds to (or changes in) the model's effects spec, which parameters are then
fitted, a probe value for the one-rollout sensitivity screen (several for a threshold), the law in words, the
residual signature it predicts (the *driver* its residual acceleration is proportional to) and what it is confused
with (``../shared/DISCOVERY.md``). A candidate applies only where the base model lacks it: linear drag is not a
discovery for a model that already has linear drag; friction is one only for a model whose ground is frictionless
and does not learn μ.
"""

from __future__ import annotations

from dataclasses import dataclass

from causalgs.errors import CausalGSError
from causalgs.sim.effects import Effects


@dataclass(frozen=True)
class Candidate:
    key: str  # short name used on the command line and in reports
    title: str  # in words
    law: str  # the law, with the parameter names as in ``params``
    effect: str  # registry effect it adds or changes
    params: tuple[str, ...]  # fitted parameter names (Effects.param_names of the changed spec)
    probe: tuple[float, ...]  # one value per parameter for the sensitivity rollout
    driver: str  # residual signature: "const", "v", "vv", "contact", "internal", "plastic"
    confused_with: tuple[str, ...] = ()
    replaces: str | None = None  # a base effect this one replaces (sticky ground replaces ground)
    start: tuple[float, ...] | None = None  # value before fitting (default 0: the effect off)
    # Further probes the screen tries (the best one counts), for an effect that acts only past a threshold: how much
    # a yield stress explains depends on how far below the rollout's stresses it is, and one probe may see no flow.
    probes: tuple[tuple[float, ...], ...] = ()

    def confused(self, other: Candidate) -> bool:
        """Whether the catalogue names ``other`` as confusable with this one (either way; by key or effect)."""
        return (other.key in self.confused_with or other.effect in self.confused_with
                or self.key in other.confused_with or self.effect in other.confused_with)  # fmt: skip

    def screen_probes(self) -> tuple[tuple[float, ...], ...]:
        """The probe values the screen tries: :attr:`probe` first, then :attr:`probes`."""
        return (self.probe, *self.probes)

    def applies(self, base: Effects, learn, changed=()) -> bool:
        """Whether this candidate is a discovery for a model with effects ``base`` learning ``learn``, after
        discoveries that added or changed the registry effects ``changed``. A structural candidate never replaces
        such an effect: sticky ground after friction would drop the friction just found, and the round that found
        it weighed sticky ground already (a structural candidate is refitted wherever it applies)."""
        names = base.names()
        if self.key == "friction":
            return "ground" in names and float(base.get("ground", "mu")[0]) == 0.0 and "ground.mu" not in learn
        if self.replaces is not None:
            return self.replaces in names and self.effect not in names and self.replaces not in changed
        return self.effect not in names

    def learn(self, base_learn) -> list[str]:
        """The effect parameters fitted with this candidate: the base's (less those of an effect it replaces) and
        its own."""
        keep = [n for n in base_learn if self.replaces is None or n.split(".")[0] != self.replaces]
        return [*keep, *[p for p in self.params if p not in keep]]

    def spec(self, base: Effects) -> str:
        """The base spec with this candidate's term added (at its start values)."""
        eff = Effects.from_spec(base.spec())
        if self.key == "friction":
            return eff.spec()  # μ is already a term of the ground; it starts at the base's 0
        parts = [p for p in eff.spec().split(";") if p and p.split(":")[0] != self.replaces]
        if self.replaces is not None and self.replaces in eff.names():
            d = float(eff.get(self.replaces, "d")[0])
            n = ",".join(repr(float(a)) for a in eff.get(self.replaces, "n"))
            parts.append(f"{self.effect}:n={n}:d={d!r}")
        else:
            start = self.start or tuple(0.0 for _ in self.params)
            vals = ",".join(repr(float(v)) for v in start)
            param = self.params[0].split(".")[1].split("[")[0]
            parts.append(f"{self.effect}:{param}={vals}")
        return ";".join(parts)


CATALOGUE: tuple[Candidate, ...] = (
    Candidate("force", "uniform force field", "a = b", "force", ("force.b[0]", "force.b[1]", "force.b[2]"),
              (0.5, 0.5, 0.5), "const", ("gravity",)),
    Candidate("linear_drag", "linear drag", "a = −c·v", "linear_drag", ("linear_drag.c",), (0.3,), "v",
              ("quadratic_drag", "damping")),
    Candidate("quadratic_drag", "quadratic drag", "a = −k·|v|·v", "quadratic_drag", ("quadratic_drag.k",), (0.3,),
              "vv", ("linear_drag",)),
    Candidate("damping", "material damping (Kelvin–Voigt viscosity)", "σ += 2·eta·sym(∇v)", "damping",
              ("damping.eta",), (30.0,), "internal", ("linear_drag",)),
    Candidate("friction", "Coulomb friction at the ground", "|Δv_t| ≤ mu·|Δv_n| at contact", "ground",
              ("ground.mu",), (0.3,), "contact", ("ground_sticky", "linear_drag")),
    Candidate("sticky", "sticky ground", "v = 0 at contact", "ground_sticky", ("ground_sticky.d",), (0.0,),
              "contact", ("friction",), replaces="ground"),
    Candidate("plasticity", "plasticity (von Mises yield)", "|dev τ| ≤ yield_stress", "plasticity",
              ("plasticity.yield_stress",), (2e3,), "plastic", (), start=(1e5,), probes=((8e3,), (5e2,))),
)  # fmt: skip

BY_KEY = {c.key: c for c in CATALOGUE}


def select(keys=None) -> list[Candidate]:
    """Candidates by key (default: the whole catalogue); an unknown key is a one-line error."""
    if keys is None:
        return list(CATALOGUE)
    out = []
    for k in keys:
        if k not in BY_KEY:
            raise CausalGSError(f"unknown candidate '{k}'; choose from: {', '.join(BY_KEY)}")
        out.append(BY_KEY[k])
    return out
