"""Figure captions, written from what each figure recorded as drawn (`reports.figures.drawn`).

A caption names only what is in the picture: no "zero contour" when the map has one sign,
no "counterexamples" when none were found, only the box colours that occur.
"""

from __future__ import annotations

from typing import Any


def _join(parts: list[str]) -> str:
    return "; ".join(p for p in parts if p) + "."


def _map_caption(what: str, d: dict[str, Any], positive: str) -> list[str]:
    """What a heatmap shows, from its record: sign colours, contour, undefined cells."""
    parts = [what]
    if "two signs" in d:
        parts.append(f"red > 0 ({positive}), blue < 0")
    elif d.get("one sign") == "negative":
        parts.append("every grid value is < 0 (blue)")
    elif d.get("one sign") == "positive":
        parts.append(f"every grid value is \u2265 0 (red: {positive})")
    if "constant" in d:
        parts.append("the value is the same at every grid point")
    if "zero contour" in d:
        parts.append("black line: zero contour")
    return parts


def caption_mpdi_map(d: dict[str, Any]) -> str:
    parts = _map_caption("max over y of \u03bb_max(D) on a grid over the first two states"
                         + (" (other states at their box centre)" if "slice" in d else ""),
                         d, "violates the MPDI")
    if "counterexamples" in d:
        parts.append(f"\u00d7 counterexamples ({d['counterexamples']})")
    if "worst point" in d:
        parts.append("\u2605 worst point found")
    if "undefined cells" in d:
        parts.append("grey: undefined")
    return _join(parts)


def caption_prover(d: dict[str, Any]) -> str:
    names = {"proved": "green proved", "violated": "red violated", "unknown": "amber unknown"}
    parts = []
    if "boxes" in d:
        shown = ", ".join(names[k] for k in names if k in d["boxes"])
        parts.append(f"Branch and bound: leaf sub-boxes projected onto the first two states "
                     f"({shown})")
    if "volume" in d:
        parts.append("proved volume over the prover's time")
    return _join(parts)


def caption_necessary_map(d: dict[str, Any]) -> str:
    parts = _map_caption("q(x\u0302) over X (independent of the network)", d,
                         "no gain meets the MPDI and the boundary condition there")
    if "witness" in d:
        parts.append("\u2605 witness: the largest q found")
    if "undefined cells" in d:
        parts.append("grey: h(x\u0302) \u2209 Y")
    return _join(parts)


def caption_residual_map(d: dict[str, Any]) -> str:
    parts = ["Boundary-condition residual \u2016k(x, h(x))\u2016 over X"]
    if "worst point" in d:
        parts.append("\u2605 largest value found")
    if "undefined cells" in d:
        parts.append("grey: undefined")
    return _join(parts)


def caption_metric_map(d: dict[str, Any]) -> str:
    parts = ["Smallest eigenvalue of the metric M(x) over X (evaluated on a grid: the proved "
             "m_min is in the section's facts)"]
    if "plant box" in d:
        parts.append("outlined: the plant box on which the stages were proved")
    if "slice" in d:
        parts.append("the other states at their box centre")
    return _join(parts)


def caption_lipschitz(d: dict[str, Any]) -> str:
    parts = ["Upper bounds (LipSDP, local interval, naive) against the sampled lower bound"]
    if "used" in d:
        parts.append("the outlined bar is the one used downstream")
    return _join(parts)
