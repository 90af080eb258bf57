"""Which parameter directions the used epochs determined, and which stayed at their prior.

The information the used epochs carried, ``I = sum H^T R^-1 H``, is compared with the prior's,
``P0^-1``, direction by direction: with ``P0 = L L^T``, the eigenvalues of ``L^T I L`` are the data's
information in units of the prior's. A direction whose ratio is below ``UNDETERMINED_RATIO`` is
reported as undetermined (it "remains at its prior"), and its eigenvector, mapped back to the
parameters, says which parameters trade off in words.
"""

from __future__ import annotations

import numpy as np

__all__ = ["UNDETERMINED_RATIO", "GROUP_SHARE", "ORDINAL", "parameter_groups", "analyse", "describe"]

#: Data-to-prior information ratio below which a direction counts as undetermined.
UNDETERMINED_RATIO = 1.0
#: Share of a direction's (prior-scaled) weight a group must carry to be named.
GROUP_SHARE = 0.1

ORDINAL = ("first", "second", "third")


def parameter_groups(names) -> list[tuple[str, list[int]]]:
    """Groups of state indices with a readable name: columns of R, the offset b, each effect."""
    groups = [(f"the {ORDINAL[j]} column of R", [3 * i + j for i in range(3)]) for j in range(3)]
    groups.append(("b", [9, 10, 11]))
    extra = {}
    for k, name in enumerate(names[12:], start=12):
        extra.setdefault(name.split(".")[0], []).append(k)
    groups += [(f"the {effect} parameters", idx) for effect, idx in extra.items()]
    return groups


def analyse(P0, information, names, R=None) -> dict:
    """Undetermined directions: ``{"undetermined": [{"ratio", "groups", "loadings", "text"}], "text"}``.

    With ``R`` (3, 3) given, a direction that is mostly a rotation ``R -> R Q`` is named as such.
    """
    P0 = np.asarray(P0, float)
    L = np.linalg.cholesky(P0)
    W = L.T @ information @ L
    w, v = np.linalg.eigh(0.5 * (W + W.T))
    findings = []
    for ratio, vec in zip(w, v.T):
        if ratio >= UNDETERMINED_RATIO:
            continue
        direction = L @ vec  # in parameter units
        share = vec**2  # weights in prior-scaled coordinates sum to 1
        groups = [g for g, idx in parameter_groups(names) if share[idx].sum() >= GROUP_SHARE]
        if R is not None and _is_rotation(direction, R):
            groups = ["the orientation of R (a rotation R -> R Q, which no magnitude can see)"]
        top = np.argsort(-np.abs(direction / np.sqrt(np.diag(P0))))[:6]
        findings.append(
            {"ratio": float(ratio), "groups": groups, "loadings": {names[i]: float(direction[i]) for i in top}}
        )
    merged = _merge(findings)
    return {"undetermined": merged, "text": describe(merged)}


def _is_rotation(direction: np.ndarray, R: np.ndarray) -> bool:
    """True when ``direction``'s R part lies (90 %) in the span of ``R Omega`` and b is untouched."""
    from .measurements import rotation_directions

    N = rotation_directions(R, 9)
    d = direction[:9]
    if np.linalg.norm(d) == 0:
        return False
    proj = N @ np.linalg.lstsq(N, d, rcond=None)[0]
    return bool(np.linalg.norm(proj) >= 0.9 * np.linalg.norm(d))


def _merge(findings: list) -> list:
    """One entry per distinct set of groups, keeping the smallest ratio and counting directions."""
    out = {}
    for f in findings:
        key = tuple(f["groups"])
        if key not in out:
            out[key] = {**f, "directions": 1}
        else:
            out[key]["directions"] += 1
            out[key]["ratio"] = min(out[key]["ratio"], f["ratio"])
    for entry in out.values():
        entry["text"] = _sentence(entry["groups"], entry["ratio"])
    return list(out.values())


def _sentence(groups, ratio) -> str:
    if not groups:
        return "a combination of parameters remains at its prior"
    if len(groups) == 1:
        verb = "remain at their" if groups[0].endswith(" parameters") else "remains at its"
        return f"{groups[0]} {verb} prior (data carried {ratio:.2g} of the prior's information)"
    joined = ", ".join(groups[:-1]) + " and " + groups[-1]
    return f"{joined} trade off; they remain at their prior (data carried {ratio:.2g} of the prior's information)"


def describe(findings) -> str:
    if not findings:
        return "all parameters are determined by the data"
    return "; ".join(f["text"] for f in findings)
