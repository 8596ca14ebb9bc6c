"""Task graph data model (paper Sec. III-B).

A task graph ``G_task = {O_target, O_anchor, R}`` holds the target noun phrases (what the task is
about), the anchor noun phrases (spatial reference objects that only constrain where a target is),
and binary relations ``r(t, a)`` with ``r`` in ``{near, on}``, ``t`` in the targets and ``a`` in the
anchors. The query set handed to the open-vocabulary detector is ``targets ∪ anchors``.

This module has no third-party dependencies and knows nothing of gRPC.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Mapping, Tuple

#: Predicates the mapper can evaluate (centroid based, paper Sec. III-B).
PREDICATES: Tuple[str, ...] = ("near", "on")


@dataclass(frozen=True)
class Relation:
    """One spatial relation ``predicate(target, anchor)``.

    Attributes:
        predicate (str): ``"near"`` or ``"on"``.
        target (str): a phrase from :attr:`TaskGraph.targets`.
        anchor (str): a phrase from :attr:`TaskGraph.anchors`.
    """

    predicate: str
    target: str
    anchor: str

    def to_dict(self) -> Dict[str, str]:
        """The relation as ``{"predicate", "target", "anchor"}`` (the shared file format)."""
        return {"predicate": self.predicate, "target": self.target, "anchor": self.anchor}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Relation":
        """Build from a mapping with string keys ``predicate``, ``target``, ``anchor``.

        Raises:
            KeyError: a key is missing.
            TypeError: a value is not a string.
        """
        vals = [data["predicate"], data["target"], data["anchor"]]
        if not all(isinstance(v, str) for v in vals):
            raise TypeError(f"relation fields must be strings: {dict(data)!r}")
        return cls(*vals)


@dataclass
class TaskGraph:
    """Object–relation graph of one task (paper Sec. III-B).

    Attributes:
        targets (list[str]): target noun phrases, lower case, singular, no determiners.
        anchors (list[str]): anchor noun phrases (never also a target).
        relations (list[Relation]): supported relations between a target and an anchor.
        unsupported (list[str]): spatial words found in the text that give no relation
            (e.g. ``"under"``, ``"left of"``).
        backend (str): which backend produced the graph, e.g. ``"rules"``, ``"openai"``,
            ``"rules(fallback from openai)"``.
        warnings (list[str]): human-readable notes (fallbacks, dropped phrases, empty input).
    """

    targets: List[str] = field(default_factory=list)
    anchors: List[str] = field(default_factory=list)
    relations: List[Relation] = field(default_factory=list)
    unsupported: List[str] = field(default_factory=list)
    backend: str = "rules"
    warnings: List[str] = field(default_factory=list)

    @property
    def query_set(self) -> List[str]:
        """``targets ∪ anchors`` in first-seen order (the detector's text queries)."""
        out: List[str] = []
        for p in list(self.targets) + list(self.anchors):
            if p not in out:
                out.append(p)
        return out

    def graph_dict(self) -> Dict[str, Any]:
        """Only the graph, exactly in the shared ``phrasings.jsonl`` format.

        ``unsupported`` is omitted when empty, like the shared files.
        """
        d: Dict[str, Any] = {
            "targets": list(self.targets),
            "anchors": list(self.anchors),
            "relations": [r.to_dict() for r in self.relations],
        }
        if self.unsupported:
            d["unsupported"] = list(self.unsupported)
        return d

    def to_dict(self, include_meta: bool = True) -> Dict[str, Any]:
        """JSON-ready dict: the graph (:meth:`graph_dict`) plus ``backend`` and, when non-empty,
        ``warnings`` unless ``include_meta`` is false."""
        d = self.graph_dict()
        if include_meta:
            d["backend"] = self.backend
            if self.warnings:
                d["warnings"] = list(self.warnings)
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], backend: str = "", warnings: Iterable[str] = ()) -> "TaskGraph":
        """Build from a dict in the shared format (``backend``/``warnings`` keys optional).

        Raises:
            KeyError, TypeError: malformed relation entries.
        """
        return cls(
            targets=[str(x) for x in data.get("targets", [])],
            anchors=[str(x) for x in data.get("anchors", [])],
            relations=[Relation.from_dict(r) for r in data.get("relations", [])],
            unsupported=[str(x) for x in data.get("unsupported", [])],
            backend=str(data.get("backend", backend)),
            warnings=[str(x) for x in data.get("warnings", list(warnings))],
        )

    def validate(self) -> List[str]:
        """Structural problems of the graph (empty list when valid).

        Checks: predicates in :data:`PREDICATES`; relation endpoints in targets/anchors; no phrase
        both a target and an anchor; no empty phrases.
        """
        errs: List[str] = []
        tset, aset = set(self.targets), set(self.anchors)
        for p in self.targets + self.anchors:
            if not p.strip():
                errs.append("empty phrase")
        both = tset & aset
        if both:
            errs.append(f"phrase(s) both target and anchor: {sorted(both)}")
        for r in self.relations:
            if r.predicate not in PREDICATES:
                errs.append(f"unknown predicate {r.predicate!r}")
            if r.target not in tset:
                errs.append(f"relation target {r.target!r} is not a target")
            if r.anchor not in aset:
                errs.append(f"relation anchor {r.anchor!r} is not an anchor")
        return errs

    def same_graph(self, other: "TaskGraph") -> bool:
        """Equality of the graphs with lists compared as sets (backend/warnings ignored)."""
        return (
            set(self.targets) == set(other.targets)
            and set(self.anchors) == set(other.anchors)
            and set(self.relations) == set(other.relations)
            and set(self.unsupported) == set(other.unsupported)
        )

    def copy(self) -> "TaskGraph":
        """A deep copy (relations are immutable, lists are copied)."""
        return TaskGraph(
            list(self.targets), list(self.anchors), list(self.relations), list(self.unsupported),
            self.backend, list(self.warnings),
        )
