"""What the box bound of max lam_max(M D M^T) is made of: one frozen `BoxBoundOptions` per
proof (or probe), made by `box_bound_options` from the problem and the caller's settings.

Everything the stages of `certify.enclose.stages` read about the problem and the prover is
here, decided once: the congruence M (`certify.enclose.preconditioner`), the constant term
M (2 lam P + Q) M^T as an interval, the technique, whether the backward linear bounds are
used, the level the bounds are held to, the split rule, and the facts about the network's
shape that choose between stages (`mixed_rows_apply`). Nothing in it changes during a proof;
a caller whose level moves (the rate prover) makes a copy with `dataclasses.replace`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch

from certify.arith.intervals import Interval
from certify.enclose.preconditioner import (
    Preconditioner,
    constant_term,
    make_preconditioner,
    with_shift,
)
from certify.enclose.split import SPLIT_RULES, split_score
from certify.model.problem import Problem

#: the remainder reduction the linear bounds are assumed to bring where no estimate was made
#: for the network (`certify.enclose.mpdi.estimate_crown_gain`): it only chooses the boxes
#: they are tried on (`certify.enclose.stages.LinearBounds`), never a bound
CROWN_GAIN = 100.0


class Technique(enum.Enum):
    """How the boxes the plain interval bound leaves are bounded."""

    #: first-order Taylor models through the network (with the linear bounds: the prover)
    TAYLOR = "taylor"
    #: mean-value form with interval second derivatives (a comparison prover)
    MEAN_VALUE = "mean-value"
    #: the plain interval bound only (the baseline)
    PLAIN = "plain"

    @classmethod
    def of(cls, taylor: bool | str | Technique) -> Technique:
        """The technique of the prover's public `taylor` keyword (`certify.prove.mpdi.
        prove_mpdi`): True the Taylor models, "interval" the mean-value form, False plain
        intervals only; a `Technique` is itself."""
        if isinstance(taylor, Technique):
            return taylor
        if taylor is True:
            return cls.TAYLOR
        if taylor is False:
            return cls.PLAIN
        if taylor == "interval":
            return cls.MEAN_VALUE
        raise ValueError(f"taylor must be True, False or 'interval', not {taylor!r}")


@dataclass
class CrownGain:
    """Remainder reduction of the linear bounds over the Taylor models, as a function of the
    box size: gains [K] measured at relative radii [K] (increasing), interpolated in log-log
    and clamped at the ends. Only decides where the linear bounds are tried."""

    rel_radii: torch.Tensor
    gains: torch.Tensor

    def at(self, rel_radius: torch.Tensor) -> torch.Tensor:
        x = torch.log(rel_radius.clamp(self.rel_radii[0], self.rel_radii[-1]))
        xs, ys = torch.log(self.rel_radii), torch.log(self.gains)
        i = torch.searchsorted(xs, x.contiguous()).clamp(1, len(xs) - 1)
        t = (x - xs[i - 1]) / (xs[i] - xs[i - 1])
        return torch.exp(ys[i - 1] + t * (ys[i] - ys[i - 1]))


def mixed_rows_apply(problem: Problem, pc: Preconditioner) -> bool:
    """Whether the mixed-row linear bounds (`certify.enclose.mixed`) enclose A = M D M^T: the
    congruence M = I with P != I (pc.kind "none", chosen by `certify.enclose.mpdi.
    choose_preconditioner`) and a direct network, whose Jacobian P dN/dx they bound with
    the rows P mixes. The one place this fact is tested; `BoxBoundOptions.mixed_rows` holds
    it. Not for the path certificate's larger matrix (a noise input): the rows it mixes are
    those of the MPDI's."""
    return (pc.kind == "none" and problem.network.structure == "direct"
            and problem.noise is None)


@dataclass(frozen=True, eq=False)
class BoxBoundOptions:
    """The box bound's settings and the facts it reads about the problem, fixed for a proof.

    Made by `box_bound_options`; the stages (`certify.enclose.stages`) say from these fields
    where they apply. Only tightness and cost depend on them, never soundness: every stage's
    bound is an upper bound of max lam_max(A) over the box whatever they are."""

    problem: Problem
    lam: float  # the rate in D = He{P J} + 2 lam P (+ Q)
    pc: Preconditioner  # the congruence A = M D M^T, carrying M Q M^T
    constant: Interval  # M (2 lam P + Q) M^T [n, n], `constant_term(pc, lam)`
    technique: Technique = Technique.TAYLOR
    #: the backward linear bounds (`certify.enclose.crown`) beside the Taylor models
    crown: bool = True
    #: `mixed_rows_apply(problem, pc)`, computed once
    mixed_rows: bool = False
    #: where the mixed rows apply: the plain interval bound screens the boxes first (the
    #: prover probes whether it pays: `certify.enclose.mpdi.plain_screen_pays`); elsewhere the
    #: plain bound always runs and this is not read
    plain_screen: bool = True
    #: boxes whose plain bound is <= screen skip the later stages; None: every stage sees
    #: every box, and the linear bounds are tried on every box the Taylor models bounded
    screen: float | None = None
    #: only "bound <= level" matters (a decision at the level, `level`): a box decided
    #: below the level may report (just below) the level instead of its eigenvalue bound
    decide: bool = False
    #: the remainder reduction assumed of the linear bounds (`CrownGain` or one number)
    crown_gain: float | CrownGain = CROWN_GAIN
    #: the root box's widths [d] (the scale of `CrownGain` and of the "widest" split rule)
    root_width: torch.Tensor | None = None
    split_rule: str = "sensitivity"  # `certify.enclose.split.SPLIT_RULES`

    @property
    def level(self) -> float:
        """The level the bounds are held to: `screen`, else 0."""
        return 0.0 if self.screen is None else self.screen

    @property
    def decide_level(self) -> float | None:
        """The level of a decision (`decide`), else None (a bound is wanted)."""
        return self.level if self.decide else None

    def split(self, taylor_score: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """The split score [B, d] of boxes with radii r [B, d] from a stage's Taylor score
        (`certify.enclose.split.split_score` under `split_rule`)."""
        return split_score(self.split_rule, taylor_score, r, self.root_width,
                           self.problem.network)


def box_bound_options(problem: Problem, lam: float, *, pc: Preconditioner | None = None,
                      technique: Technique = Technique.TAYLOR, crown: bool = True,
                      screen: float | None = None, decide: bool = False,
                      plain_screen: bool = True, crown_gain: float | CrownGain = CROWN_GAIN,
                      root_width: torch.Tensor | None = None,
                      split_rule: str = "sensitivity") -> BoxBoundOptions:
    """The `BoxBoundOptions` of `problem` at rate `lam`: `pc` default M ~ L^-1 (P = L L^T)
    with the problem's constant term Q; the constant term and the network-shape facts are
    computed here, once (field docs for the rest)."""
    if split_rule not in SPLIT_RULES:
        raise ValueError(f"split_rule must be one of {SPLIT_RULES}, not {split_rule!r}")
    if pc is None:
        pc = with_shift(make_preconditioner(problem.P_t), problem.shift_t)
    return BoxBoundOptions(problem=problem, lam=float(lam), pc=pc,
                           constant=constant_term(pc, lam), technique=Technique.of(technique),
                           crown=bool(crown), mixed_rows=mixed_rows_apply(problem, pc),
                           plain_screen=bool(plain_screen), screen=screen, decide=bool(decide),
                           crown_gain=crown_gain, root_width=root_width,
                           split_rule=split_rule)
