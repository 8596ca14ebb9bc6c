"""The rule parser's lexicon (:mod:`gausslite.parser.rules`, which re-exports it): text normalisation
(:func:`normalize_text`), singularisation (:func:`singularize_word`, :func:`singularize_phrase`), the word classes of
the grammar (determiners, fillers, pronouns, coordinators, scope, path and part words, leading words, particles), the
relation phrases (:data:`REL_TABLE`) and the verbs with their inflected forms (:func:`verb_base`).

Pure Python, built once at import.
"""

from __future__ import annotations

import re
from typing import Dict, FrozenSet, List, Optional, Sequence, Tuple


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

#: Relations: token tuple → (kind, canonical word). kind: near | on | unsup | dest | drop
REL_TABLE: Dict[Tuple[str, ...], Tuple[str, str]] = {}


def _rel(kind: str, canon: str, *phrases: str) -> None:
    for p in phrases:
        REL_TABLE[tuple(p.split())] = (kind, canon)


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
#: tokens of the longest relation phrase
REL_MAXLEN = max(len(k) for k in REL_TABLE)

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
#: forms of known verbs read as participles that describe an object ("the cup lying on the desk"), never as a verb
NOT_VERB_FORMS = frozenset(["found", "kept", "set", "put", "seen", "left", "lying", "sitting", "standing",
                             "placed", "stored", "parked", "mounted", "hanging"])


def verb_base(tok: str) -> Optional[str]:
    """Base form of a known verb token (``"avoiding"`` → ``"avoid"``), else ``None``."""
    return _VERB_FORMS.get(tok)


def is_pure_verb(tok: str) -> bool:
    """Whether ``tok`` is the base or ``-ing`` form of a verb that is (practically) never a noun
    (:data:`PURE_VERBS`): such a token splits clauses anywhere."""
    base = _VERB_FORMS.get(tok)
    if base is None or base not in PURE_VERBS:
        return False
    # Only base and -ing forms split clauses ("takes"/"looks" are too easily nouns or 3sg).
    return tok == base or tok.endswith("ing")
