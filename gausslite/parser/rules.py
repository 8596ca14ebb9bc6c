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

import re
from dataclasses import dataclass, field
from typing import Dict, FrozenSet, Iterable, List, Optional, Sequence, Set, Tuple

from .graph import Relation, TaskGraph

# --------------------------------------------------------------------------------------------
# Text normalisation
# --------------------------------------------------------------------------------------------

_CONTRACTIONS: Dict[str, str] = {
    "let's": "let us", "lets": "let us", "i'd": "i would", "i'm": "i am", "we'd": "we would",
    "you'd": "you would", "can't": "can not", "cannot": "can not", "don't": "do not",
    "doesn't": "does not", "won't": "will not", "isn't": "is not", "aren't": "are not",
    "what's": "what is", "where's": "where is", "there's": "there is", "that's": "that is",
    "it's": "it is", "i'll": "i will", "we'll": "we will", "you'll": "you will",
}
_WORD_RE = re.compile(r"[a-z0-9]+(?:['-][a-z0-9]+)*|[/,]")


def normalize_text(text: str) -> str:
    """Normalise a task string: the cache key and the input of the rule parser.

    Lower case; typographic quotes folded; ``&`` → ``and``; sentence punctuation (``. ! ? ; :``)
    becomes a clause separator ``,``; ``/`` and ``,`` are kept as separate tokens because they change
    the parse; every other punctuation character is stripped; contractions expanded; possessive
    ``'s`` dropped; whitespace collapsed; leading/trailing separators removed.

    Args:
        text (str): free-form task text.
    Returns:
        str: the normalised text (possibly empty).
    """
    t = text.lower().replace("\u2019", "'").replace("\u2018", "'").replace("&", " and ")
    t = re.sub(r"[.!?;:]+(?=\s|$)", " , ", t)
    toks: List[str] = []
    for w in _WORD_RE.findall(t):
        if w in _CONTRACTIONS:
            toks.extend(_CONTRACTIONS[w].split())
            continue
        if w.endswith("'s"):
            w = w[:-2]
        w = w.replace("'", "")
        if w:
            toks.append(w)
    # collapse runs of separators and trim them at both ends
    out: List[str] = []
    for w in toks:
        if w in (",", "/") and (not out or out[-1] in (",", "/")):
            if out and w == "," and out[-1] == "/":
                out[-1] = ","
            continue
        out.append(w)
    while out and out[-1] in (",", "/"):
        out.pop()
    return " ".join(out)


# --------------------------------------------------------------------------------------------
# Singularisation
# --------------------------------------------------------------------------------------------

_IRREGULAR: Dict[str, str] = {
    "people": "person", "mice": "mouse", "children": "child", "men": "man", "women": "woman",
    "feet": "foot", "teeth": "tooth", "geese": "goose", "dice": "die", "cacti": "cactus",
    "knives": "knife", "shelves": "shelf", "leaves": "leaf", "loaves": "loaf", "wolves": "wolf",
    "halves": "half", "calves": "calf", "scarves": "scarf", "lives": "life", "wives": "wife",
    "thieves": "thief", "elves": "elf", "hooves": "hoof", "bookshelves": "bookshelf",
    "movies": "movie", "cookies": "cookie", "pies": "pie", "ties": "tie", "hoodies": "hoodie",
    "zombies": "zombie", "brownies": "brownie", "selfies": "selfie", "headaches": "headache",
    "caches": "cache", "niches": "niche", "buses": "bus", "gases": "gas", "lenses": "lens",
    "bonuses": "bonus", "cactuses": "cactus", "viruses": "virus", "circuses": "circus",
    "potatoes": "potato", "tomatoes": "tomato", "heroes": "hero", "echoes": "echo",
    "mosquitoes": "mosquito", "volcanoes": "volcano", "torpedoes": "torpedo", "indices": "index",
    "matrices": "matrix", "vertices": "vertex", "axes": "axis", "oxen": "ox", "criteria": "criterion",
    "phenomena": "phenomenon", "data": "data", "media": "medium",
}
_INVARIANT: FrozenSet[str] = frozenset(
    "gas lens canvas atlas bias alias iris chaos species series news means scissors pliers tongs "
    "pants jeans shorts trousers clothes binoculars headquarters dirt trash debris sheep fish deer "
    "aircraft furniture equipment luggage glass grass dress chess this its is has was yes".split()
)


def singularize_word(word: str) -> str:
    """Singular form of one English noun (rule based; irregulars from a table).

    Examples: ``shelves→shelf``, ``boxes→box``, ``glasses→glass``, ``benches→bench``,
    ``knives→knife``, ``people→person``, ``mice→mouse``, ``keys→key``, ``batteries→battery``.
    Words that are not plural are returned unchanged.
    """
    w = word
    if w in _IRREGULAR:
        return _IRREGULAR[w]
    for suffix in ("women", "men"):  # firemen, snowmen, chairwomen
        if w.endswith(suffix) and len(w) > len(suffix) + 2 and w not in ("specimen", "abdomen"):
            return w[: -len(suffix)] + suffix.replace("e", "a")
    if w in _INVARIANT or len(w) < 3 or not w.isalpha():
        return w
    if w.endswith(("ss", "us", "is", "ous")):
        return w
    if w.endswith("ies") and len(w) > 4:
        return w[:-3] + "y"
    if w.endswith(("ches", "shes", "sses", "xes", "zzes", "zes")) and len(w) > 4:
        if w.endswith("zes") and not w.endswith("zzes"):
            return w[:-1]  # sizes, prizes → size, prize
        return w[:-2]
    if w.endswith("s") and not w.endswith("ss"):
        return w[:-1]
    return w


def singularize_phrase(words: Sequence[str]) -> List[str]:
    """Singularise the head of a noun phrase: the word before ``of`` if present, else the last."""
    ws = list(words)
    if not ws:
        return ws
    head = ws.index("of") - 1 if "of" in ws[1:] else len(ws) - 1
    if head >= 0:
        ws[head] = singularize_word(ws[head])
    return ws


# --------------------------------------------------------------------------------------------
# Lexicon
# --------------------------------------------------------------------------------------------

DETERMINERS: FrozenSet[str] = frozenset(
    "the a an all every any this that these those some each both either neither my your our its "
    "their his her another several few many much more most no such what which whatever "
    "one two three four five six seven eight nine ten eleven twelve dozen couple pair lot lots "
    "bunch number".split()
)
#: Adjectives that do not identify an object (size, order, vagueness); dropped before the head.
DROP_ADJECTIVES: FrozenSet[str] = frozenset(
    "big small large little tiny huge giant nearby other same certain particular specific "
    "nearest closest first second third last remaining entire whole visible various different "
    "given mentioned".split()
)
#: Words that are never part of a noun phrase (adverbs, politeness).
FILLER_ADVERBS: FrozenSet[str] = frozenset(
    "please now immediately quickly carefully slowly gently again also too just here there "
    "currently kindly safely first finally afterwards later soon somewhere anywhere".split()
)
PRONOUNS: FrozenSet[str] = frozenset("it them me us you him i we they yourself itself themselves".split())
COORD: FrozenSet[str] = frozenset(["and", "or", "/", "nor", "plus", "as well as"])
RELATIVE: FrozenSet[str] = frozenset(["that", "which", "who", "where", "whose"])
#: Words between a noun phrase and a relation word ("the cup (that is) sitting on ...").
FILLERS: FrozenSet[str] = frozenset(
    "is are was were be being been located placed sitting lying resting standing kept situated "
    "positioned found stored left lies sits rests stands hanging hangs leaning set seen put "
    "laying lay parked mounted".split()
)
NEGATION: FrozenSet[str] = frozenset(["not", "except", "excluding", "besides", "never"])
#: Scope words: where the task happens, never an object.
SCOPE_WORDS: FrozenSet[str] = frozenset(
    "scene room area environment space surroundings surrounding vicinity map world house home "
    "building place region workspace everywhere site view frame premises".split()
)
#: Path words: never an object; their destination is the target.
PATH_WORDS: FrozenSet[str] = frozenset("path way route trajectory course".split())
#: Part words: "the edge of the table" → "table".
PART_WORDS: FrozenSet[str] = frozenset(
    "top bottom edge side corner end middle center centre surface front back rest".split()
)

# Relations: token tuple → (kind, canonical word). kind: near | on | unsup | dest | drop
_REL_TABLE: Dict[Tuple[str, ...], Tuple[str, str]] = {}


def _rel(kind: str, canon: str, *phrases: str) -> None:
    for p in phrases:
        _REL_TABLE[tuple(p.split())] = (kind, canon)


_rel("near", "near", "near", "near to", "next to", "right next to", "beside", "by", "close to",
     "closest to", "nearest to", "nearest", "closest", "around", "at", "adjacent to", "alongside",
     "along", "close by", "nearby", "right by", "right beside", "next by", "near by")
_rel("on", "on", "on", "on top of", "upon", "onto", "atop", "from", "off", "off of", "on to",
     "from on top of", "right on")
for _w in ("under", "underneath", "beneath", "inside", "in", "within", "behind", "above", "below",
           "between", "among", "amongst", "over", "opposite", "against", "outside", "beyond"):
    _rel("unsup", _w, _w)
_rel("unsup", "inside", "inside of")
_rel("unsup", "outside", "outside of")
_rel("unsup", "in front of", "in front of")
_rel("unsup", "across from", "across from")
_rel("unsup", "opposite", "opposite to", "opposite of")
_rel("unsup", "left of", "left of", "to the left of", "on the left of", "at the left of", "on the left side of",
     "to the left side of")
_rel("unsup", "right of", "right of", "to the right of", "on the right of", "at the right of",
     "on the right side of", "to the right side of")
_rel("dest", "to", "to", "away from", "towards", "toward", "into", "for", "through", "past", "up to", "over to")
_rel("drop", "with", "with", "using", "via", "like")
_REL_MAXLEN = max(len(k) for k in _REL_TABLE)

#: Verbs that are (practically) never nouns: they split clauses anywhere.
PURE_VERBS: FrozenSet[str] = frozenset(
    "avoid locate identify navigate fetch grab bring inspect retrieve find go dodge bypass pick "
    "detect collect explore visit proceed reach look take get approach circumvent evade "
    "hit touch bump collide knock disturb prepare".split()
)
#: Verbs that can also be nouns ("map", "water", "check"); they only split clauses after and/or
#: when a determiner, particle or pronoun follows.
AMBIGUOUS_VERBS: FrozenSet[str] = frozenset(
    "map water check monitor watch clear clean place set drop charge wash open close mark count "
    "scan survey move point hand show turn switch light fill empty store stack sort return head "
    "track search hold push pull lift carry put deliver give help keep stay steer walk drive sit "
    "stand follow observe examine see view photograph capture record reconstruct model label "
    "segment measure throw toss feed fix repair replace arrange fold hang press plug unplug pack "
    "unpack load unload make let start begin continue need want try remove tidy organize organise "
    "gather spot highlight focus attend wait park dock guide lead escort transport relocate "
    "rearrange grasp seize obtain acquire recover pass slide rotate align position tap aim "
    "wipe dust vacuum mop sweep stop skip ignore come move reach study note describe".split()
)
ALL_VERBS: FrozenSet[str] = PURE_VERBS | AMBIGUOUS_VERBS
PARTICLES: FrozenSet[str] = frozenset(
    "up down out over for to at on onto into toward towards around away back from off of after "
    "with by in through across along clear ahead about".split()
)
#: Words skipped at the start of a clause (politeness, subjects, modals, question words).
LEAD_WORDS: FrozenSet[str] = frozenset(
    "please kindly could can would will should must shall may might you we i need needs want wants "
    "like to then first next finally also now and or so okay ok hey robot just let us am "
    "where what is are there how do does did see spot go ahead sure make be try required tasked "
    "asked your job task goal mission".split()
)
#: Gerund/inflection → base form of every known verb.
_VERB_FORMS: Dict[str, str] = {}
for _v in ALL_VERBS:
    forms = {_v, _v + "s", _v + "es", _v + "ing", _v + "ed"}
    if _v.endswith("e"):
        forms |= {_v[:-1] + "ing", _v + "d"}
    if len(_v) >= 3 and _v[-1] not in "aeiouwxy" and _v[-2] in "aeiou" and _v[-3] not in "aeiou":
        forms |= {_v + _v[-1] + "ing", _v + _v[-1] + "ed"}
    for f in forms:
        _VERB_FORMS.setdefault(f, _v)
for _f, _v in {"went": "go", "goes": "go", "going": "go", "brought": "bring", "took": "take",
               "found": "find", "got": "get", "seen": "see", "held": "hold", "kept": "keep",
               "caught": "catch"}.items():
    _VERB_FORMS[_f] = _v
_NOT_VERB_FORMS = frozenset(["found", "kept", "set", "put", "seen", "left", "lying", "sitting", "standing",
                             "placed", "stored", "parked", "mounted", "hanging"])


def verb_base(tok: str) -> Optional[str]:
    """Base form of a known verb token (``"avoiding"`` → ``"avoid"``), else ``None``."""
    return _VERB_FORMS.get(tok)


def _is_pure_verb(tok: str) -> bool:
    base = _VERB_FORMS.get(tok)
    if base is None or base not in PURE_VERBS:
        return False
    # Only base and -ing forms split clauses ("takes"/"looks" are too easily nouns or 3sg).
    return tok == base or tok.endswith("ing")


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
    for n in range(min(_REL_MAXLEN, len(toks) - i), 0, -1):
        hit = _REL_TABLE.get(tuple(toks[i : i + n]))
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
    if base is None or tok in _NOT_VERB_FORMS:
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
        if cur and _is_pure_verb(tok):
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
        if base is not None and tok not in _NOT_VERB_FORMS and (i + 1 < n or base in PURE_VERBS):
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
        if words and _is_pure_verb(tok):
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
