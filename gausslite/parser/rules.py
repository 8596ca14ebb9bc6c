"""Deterministic rule/grammar task parser — the default, offline backend (paper Sec. III-B).

The paper extracts ``{targets, anchors, relations}`` with a few-shot prompted LLM; this module does
the same job with a small hand-written grammar so that nothing has to be downloaded. It follows the
normalisation rules in ``docs/mapper.md`` ("Task graphs").

Grammar (over lower-case word tokens, see :func:`normalize_text`)::

    task     := clause (BOUNDARY clause)*
    clause   := LEAD* (VERB PARTICLE*)* np_list
    np_list  := np ((COORD | RELATION | DEST | FILLER* RELATION) np)*
    np       := DET* DROP_ADJ* word+ ("of" word+)?

* ``BOUNDARY``: ``, ; then while whilst but before after once without``, an ``and``/``or`` that is
  followed by a verb, and an unambiguous verb (``avoiding``, ``grab`` ...) in the middle of a clause.
* ``VERB``: imperative verbs (base form, ``-ing`` or ``-s``) are skipped together with their
  particles and object pronouns ("pick up", "bring me", "go to", "prepare to sit on"). An unknown
  first word directly followed by a determiner is treated as a verb too ("water the plants").
* ``RELATION``: ``near`` synonyms (near, next to, beside, by, closest to, nearest, around, close
  to, at, ...) and ``on`` synonyms (on, on top of, sitting on, from, off, ...) give relations;
  other spatial words (under, inside, in, behind, left of, right of, above, below, between, ...)
  give an anchor and an ``unsupported`` entry but no relation.
* A noun phrase after a relation is an anchor; any other noun phrase is a target. Coordination
  (``and``, ``or``, ``/``) repeats the role; after an anchor only ``or``/``/`` (or ``and`` after
  ``between``/``among``) continue the anchors, a plain ``and`` starts new targets.
* Scope words (scene, room, area, environment, ...) are never objects: "in the scene" is dropped
  without an ``unsupported`` entry. Path words (path, way, route) are never objects: their
  destination becomes a target ("find a path to the door" → ``door``).
* Phrases are singularised on their head word (the last word, or the word before ``of``).

Everything is pure Python; one parse is well under a millisecond.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, List, Optional, Sequence, Set, Tuple

from .graph import Relation, TaskGraph
# the lexicon lives in a module of its own; its names import from here as before
from .lexicon import (ALL_VERBS, AMBIGUOUS_VERBS, COORD, DETERMINERS, DROP_ADJECTIVES, FILLER_ADVERBS,  # noqa: F401
                      FILLERS, LEAD_WORDS, NEGATION, NOT_VERB_FORMS, PART_WORDS, PARTICLES, PATH_WORDS, PRONOUNS,
                      PURE_VERBS, REL_MAXLEN, REL_TABLE, RELATIVE, SCOPE_WORDS, is_pure_verb, normalize_text,
                      singularize_phrase, singularize_word, verb_base)

# --------------------------------------------------------------------------------------------
# Parser
# --------------------------------------------------------------------------------------------


@dataclass
class _Acc:
    targets: List[str] = field(default_factory=list)
    anchors: List[str] = field(default_factory=list)
    relations: List[Relation] = field(default_factory=list)
    unsupported: List[str] = field(default_factory=list)
    negated: List[str] = field(default_factory=list)
    warnings: List[str] = field(default_factory=list)

    @staticmethod
    def _add(lst: List[str], item: str) -> None:
        if item not in lst:
            lst.append(item)


def _match_rel(toks: Sequence[str], i: int) -> Optional[Tuple[str, str, int]]:
    """Longest relation phrase starting at ``i``: (kind, canonical, end index)."""
    for n in range(min(REL_MAXLEN, len(toks) - i), 0, -1):
        hit = REL_TABLE.get(tuple(toks[i : i + n]))
        if hit is not None:
            return hit[0], hit[1], i + n
    return None


def _next_is_np_start(toks: Sequence[str], j: int) -> bool:
    return j < len(toks) and (toks[j] in DETERMINERS or toks[j] in PRONOUNS or toks[j] in PARTICLES)


def _starts_clause(toks: Sequence[str], i: int) -> bool:
    """True when ``toks[i]`` (a verb) begins a new clause after a coordinator."""
    tok = toks[i]
    if tok in ("then", "afterwards"):
        return True
    base = verb_base(tok)
    if base is None or tok in NOT_VERB_FORMS:
        return False
    if base in PURE_VERBS:
        return True
    return _next_is_np_start(toks, i + 1)


_HARD_BOUNDARIES = frozenset([",", "then", "while", "whilst", "but", "before", "after", "once",
                              "without", "afterwards", "until", "so", "because", "if", "when", "whenever",
                              "meanwhile", "ensuring", "making"])


def split_clauses(toks: Sequence[str]) -> List[List[str]]:
    """Split a token list into clauses (see the module grammar)."""
    clauses: List[List[str]] = [[]]
    for i, tok in enumerate(toks):
        cur = clauses[-1]
        if tok in _HARD_BOUNDARIES:
            if tok == "after" and cur and cur[-1] in ("look", "looking", "go"):
                cur.append(tok)  # "look after the plants"
                continue
            clauses.append([])
            continue
        if tok in ("and", "or") and i + 1 < len(toks) and _starts_clause(toks, i + 1):
            clauses.append([])
            continue
        if cur and is_pure_verb(tok):
            prev = cur[-1]
            # "pick" needs a following particle/determiner to be a verb mid-clause
            if prev not in DETERMINERS and (tok not in ("pick", "look", "reach", "take", "get", "go")
                                            or _next_is_np_start(toks, i + 1)):
                clauses.append([tok])
                continue
        cur.append(tok)
    return [c for c in clauses if c]


def _strip_lead(toks: Sequence[str]) -> Tuple[int, bool]:
    """Skip politeness, subjects, modals and the verb group. Returns (index, verb_seen)."""
    i, n, verb_seen = 0, len(toks), False
    while i < n:
        tok = toks[i]
        if tok == "next" and i + 1 < n and toks[i + 1] == "to":
            break
        if tok in LEAD_WORDS and i + 1 < n and not (tok in ("can", "spot", "map") and toks[i + 1] in PARTICLES):
            # "go" / "see" / "spot" / "try" are verbs too: mark them
            if verb_base(tok):
                verb_seen = True
            i += 1
            continue
        if tok in FILLER_ADVERBS:
            i += 1
            continue
        base = verb_base(tok)
        if base is not None and tok not in NOT_VERB_FORMS and (i + 1 < n or base in PURE_VERBS):
            verb_seen = True
            i += 1
            # particles and object pronouns of the verb: "pick up", "bring me", "go to", "sit on"
            while i < n and (toks[i] in PARTICLES or toks[i] in PRONOUNS or toks[i] in FILLER_ADVERBS):
                i += 1
            continue
        if (
            not verb_seen
            and i + 1 < n
            and tok.isalpha()
            and tok not in DETERMINERS
            and tok not in PRONOUNS
            and tok not in NEGATION
            and _match_rel(toks, i) is None
            and toks[i + 1] in DETERMINERS
        ):
            verb_seen = True  # unknown verb followed by a determiner: "water the plants"
            i += 1
            continue
        break
    return i, verb_seen


def _parse_np(toks: Sequence[str], i: int) -> Tuple[Optional[str], int, bool]:
    """Parse one noun phrase at ``i``. Returns (phrase or None, end index, proximity adjective seen)."""
    n = len(toks)
    words: List[str] = []
    prox = False
    j = i
    while j < n:
        tok = toks[j]
        if not words:
            if tok in DETERMINERS:
                j += 1
                if j < n and toks[j] == "of":  # "all of the", "a pair of"
                    j += 1
                continue
            if tok in ("nearest", "closest"):
                prox = True
                j += 1
                continue
            if tok in DROP_ADJECTIVES or tok in FILLER_ADVERBS or tok.isdigit():
                j += 1
                continue
            if tok in PART_WORDS and j + 1 < n and toks[j + 1] == "of":
                j += 2
                continue
            if tok in PRONOUNS:
                return None, j + 1, prox
        if tok in COORD or tok == "," or tok in NEGATION:
            break
        if words and (tok in DETERMINERS or tok in RELATIVE or tok in FILLERS or tok in PRONOUNS):
            break
        if tok in FILLER_ADVERBS:
            break
        if _match_rel(toks, j) is not None and not (words and words[-1] == "of"):
            break
        if tok == "of" and not words:
            break
        if tok == "of" and (j + 1 >= n or _match_rel(toks, j + 1) is not None):
            break
        if words and is_pure_verb(tok):
            break
        words.append(tok)
        j += 1
    while words and words[-1] == "of":
        words.pop()
    if not words:
        return None, j, prox
    phrase_words = singularize_phrase(words)
    return " ".join(phrase_words), j, prox


def _is_scope(phrase: str) -> bool:
    return all(w in SCOPE_WORDS for w in phrase.split())


def _is_path(phrase: str) -> bool:
    return phrase.split()[-1] in PATH_WORDS


def _parse_clause(toks: Sequence[str], acc: _Acc) -> None:
    i, verb_seen = _strip_lead(toks)
    n = len(toks)
    if i == 0 and not verb_seen and toks and toks[0] not in DETERMINERS and _match_rel(toks, 0) is None \
            and toks[0] not in NEGATION:
        acc.warnings.append(f"no verb recognised in '{' '.join(toks)}'; parsed as a noun phrase")
    role = "target"  # target | anchor | drop
    rel: Optional[Tuple[str, str]] = None
    group: List[str] = []
    parsed_any = False
    negated = False
    pending_path = False
    while i < n:
        tok = toks[i]
        m = _match_rel(toks, i)
        if m is not None:
            kind, canon, j = m
            # merge stacked prepositions: "from under", "from on top of"
            m2 = _match_rel(toks, j)
            while m2 is not None and m2[0] in ("near", "on", "unsup") and kind in ("on", "dest", "near"):
                kind, canon, j = m2
                m2 = _match_rel(toks, j)
            i = j
            if pending_path or (verb_seen and not parsed_any and kind in ("near", "on")):
                role, rel, group = "target", None, []
                pending_path = False
                continue
            if kind in ("near", "on", "unsup"):
                role, rel = "anchor", (kind, canon)
            elif kind == "dest":
                role, rel, group = "target", None, []
            else:  # drop: "with a cloth"
                role, rel = "drop", None
            continue
        if tok in COORD:
            if role == "anchor" and tok == "and" and not (rel and rel[1] in ("between", "among", "amongst")):
                role, rel, group = "target", None, []
            elif role == "drop":
                role = "target"
            i += 1
            continue
        if tok in NEGATION:
            negated = True
            i += 1
            continue
        if tok in RELATIVE and parsed_any:
            # skip a relative clause up to its relation word: "the cup that I left on the table"
            j = i + 1
            while j < n and _match_rel(toks, j) is None and toks[j] not in COORD:
                j += 1
            if j < n and _match_rel(toks, j) is not None and _match_rel(toks, j)[0] == "dest":
                j = n  # "that leads to ..." is not a location
            i = j
            continue
        if tok in FILLERS or tok in FILLER_ADVERBS or tok == "," or tok in RELATIVE:
            i += 1
            continue
        phrase, j, prox = _parse_np(toks, i)
        if j == i:
            i += 1
            continue
        i = j
        if phrase is None:
            continue
        parsed_any = True
        if _is_scope(phrase):
            continue
        if _is_path(phrase):
            pending_path = True
            continue
        if negated:
            acc._add(acc.negated, phrase)
            continue
        if role == "target":
            acc._add(acc.targets, phrase)
            if phrase not in group:
                group.append(phrase)
            if prox and i < n and toks[i] == "to":  # "the closest chair to the table"
                role, rel = "anchor", ("near", "near")
                i += 1
        elif role == "anchor" and rel is not None:
            acc._add(acc.anchors, phrase)
            kind, canon = rel
            if kind == "unsup":
                acc._add(acc.unsupported, canon)
            else:
                for t in group:
                    if t != phrase:
                        r = Relation(kind, t, phrase)
                        if r not in acc.relations:
                            acc.relations.append(r)
        # role == "drop": instrument/attribute phrase, ignored


def _finalize(acc: _Acc) -> TaskGraph:
    warnings = list(acc.warnings)
    targets = list(acc.targets)
    anchors = list(acc.anchors)
    anchored = {r.anchor for r in acc.relations}
    for p in [t for t in targets if t in anchors]:
        if p in anchored:
            targets.remove(p)
            warnings.append(f"'{p}' is both a target and an anchor; kept as anchor")
        else:
            anchors.remove(p)
            warnings.append(f"'{p}' is both a target and an anchor; kept as target")
    rels = [r for r in acc.relations if r.target in targets and r.anchor in anchors]
    if len(rels) != len(acc.relations):
        warnings.append("dropped relation(s) whose target became an anchor")
    if acc.negated:
        warnings.append("negated phrase(s) ignored: " + ", ".join(acc.negated))
    if not targets:
        warnings.append("no target object found in the task text")
    return TaskGraph(targets, anchors, rels, list(acc.unsupported), backend="rules", warnings=warnings)


class RuleParser:
    """Deterministic grammar parser (the default backend; paper Sec. III-B).

    Thread safe and stateless. ``parse`` never raises on any ``str`` input.
    """

    name = "rules"

    def parse(self, text: str) -> TaskGraph:
        """Parse a task text into a :class:`TaskGraph`.

        Args:
            text (str): free-form task text (any string; empty/garbage gives an empty graph with
                a warning).
        Returns:
            TaskGraph: ``backend == "rules"``.
        Raises:
            TypeError: ``text`` is not a ``str``.
        """
        if not isinstance(text, str):
            raise TypeError(f"task text must be str, got {type(text).__name__}")
        norm = normalize_text(text)
        acc = _Acc()
        if not norm or not any(c.isalpha() for c in norm):
            return TaskGraph(backend="rules", warnings=["empty task text: no words to parse"])
        for clause in split_clauses(norm.split()):
            _parse_clause(clause, acc)
        return _finalize(acc)


def text_vocabulary(text: str) -> Set[str]:
    """Words of the normalised ``text`` plus their singular forms (for grounding checks)."""
    words = [w for w in normalize_text(text).split() if w not in (",", "/")]
    vocab = set(words)
    vocab.update(singularize_word(w) for w in words)
    return vocab


def is_grounded(phrase: str, vocab: Iterable[str]) -> bool:
    """True when every word of ``phrase`` occurs in ``vocab`` (see :func:`text_vocabulary`)."""
    v = vocab if isinstance(vocab, (set, frozenset)) else set(vocab)
    words = phrase.split()
    return bool(words) and all(w in v or singularize_word(w) in v for w in words)


def parse_rules(text: str) -> TaskGraph:
    """Convenience: ``RuleParser().parse(text)``."""
    return RuleParser().parse(text)
