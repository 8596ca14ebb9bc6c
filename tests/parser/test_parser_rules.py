"""Rule parser: shared phrasings, dataset task files, extra everyday phrasings, robustness."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gausslite.parser import RuleParser, TaskGraph, normalize_text, singularize_word
from gausslite.parser.graph import Relation
from gausslite.parser.rules import is_grounded, text_vocabulary

P = RuleParser()


def _shared_items(shared_dir):
    items = [json.loads(line) for line in (shared_dir / "tasks" / "phrasings.jsonl").read_text().splitlines()
             if line.strip()]
    for name in ("Replica_room0", "TUM_rgbd_dataset_freiburg1_rpy"):
        data = json.loads((shared_dir / "datasets" / name / "tasks.json").read_text())
        items += [{"text": t["text"], "graph": t["graph"]} for t in data["tasks"]]
    return items


def test_shared_phrasings_exact(tasks_dir):
    lines = [json.loads(x) for x in (tasks_dir / "phrasings.jsonl").read_text().splitlines() if x.strip()]
    assert len(lines) >= 20
    for item in lines:
        got = P.parse(item["text"])
        exp = TaskGraph.from_dict(item["graph"])
        assert got.same_graph(exp), f"{item['text']!r}: got {got.graph_dict()} expected {item['graph']}"
        assert got.validate() == []
        # graph_dict matches the shared format exactly up to list order
        gd = got.graph_dict()
        assert set(gd) == set(item["graph"])


@pytest.mark.parametrize("name", ["Replica_room0", "TUM_rgbd_dataset_freiburg1_rpy"])
def test_dataset_tasks_json(shared_dir, name):
    path = shared_dir / "datasets" / name / "tasks.json"
    if not path.exists():
        pytest.skip(f"missing {path}")
    data = json.loads(path.read_text())
    assert data["tasks"]
    for t in data["tasks"]:
        got = P.parse(t["text"])
        assert got.same_graph(TaskGraph.from_dict(t["graph"])), (t["text"], got.graph_dict())


def _rels(*specs):
    out = set()
    for s in specs:
        pred, rest = s.split(":")
        t, a = rest.split(">")
        out.add(Relation(pred, t, a))
    return out


# (text, targets, anchors, relations "pred:target>anchor", unsupported)
EXTRA = [
    ("Please pick up the blue mug on the kitchen table.", ["blue mug"], ["kitchen table"], ["on:blue mug>kitchen table"], []),
    ("Could you grab the wooden chairs next to the window?", ["wooden chair"], ["window"], ["near:wooden chair>window"], []),
    ("Fetch the knives from the drawer", ["knife"], ["drawer"], ["on:knife>drawer"], []),
    ("Bring me the glasses on top of the shelves", ["glass"], ["shelf"], ["on:glass>shelf"], []),
    ("Locate the people near the benches", ["person"], ["bench"], ["near:person>bench"], []),
    ("Identify every mouse beside the laptops", ["mouse"], ["laptop"], ["near:mouse>laptop"], []),
    ("Map all boxes by the door", ["box"], ["door"], ["near:box>door"], []),
    ("Reach for the bottle at the sink", ["bottle"], ["sink"], ["near:bottle>sink"], []),
    ("Go to the fridge", ["fridge"], [], [], []),
    ("Navigate to the charging station while avoiding the boxes", ["charging station", "box"], [], [], []),
    ("Avoid the cables under the desk", ["cable"], ["desk"], [], ["under"]),
    ("Inspect the painting above the sofa", ["painting"], ["sofa"], [], ["above"]),
    ("Look for the cat behind the curtain", ["cat"], ["curtain"], [], ["behind"]),
    ("Check the shoes inside the closet", ["shoe"], ["closet"], [], ["inside"]),
    ("Find the remote in the drawer", ["remote"], ["drawer"], [], ["in"]),
    ("Find the lamp between the sofa and the armchair", ["lamp"], ["sofa", "armchair"], [], ["between"]),
    ("Grab the cup to the left of the plate", ["cup"], ["plate"], [], ["left of"]),
    ("Pick up the pen to the right of the notebook", ["pen"], ["notebook"], [], ["right of"]),
    ("Locate the rug below the table", ["rug"], ["table"], [], ["below"]),
    ("Find the book on the table and then bring it to me", ["book"], ["table"], ["on:book>table"], []),
    ("Grab the apples/oranges on the counter", ["apple", "orange"], ["counter"], ["on:apple>counter", "on:orange>counter"], []),
    ("Find the mug or the cup on the desk", ["mug", "cup"], ["desk"], ["on:mug>desk", "on:cup>desk"], []),
    ("Pick up the red cups and the plates on the table", ["red cup", "plate"], ["table"], ["on:red cup>table", "on:plate>table"], []),
    ("Locate the nearest chair to the door", ["chair"], ["door"], ["near:chair>door"], []),
    ("Find the chair nearest the door", ["chair"], ["door"], ["near:chair>door"], []),
    ("Pick up the phone resting on the nightstand", ["phone"], ["nightstand"], ["on:phone>nightstand"], []),
    ("Find the keys lying on the floor", ["key"], ["floor"], ["on:key>floor"], []),
    ("Grab the towel off the rack", ["towel"], ["rack"], ["on:towel>rack"], []),
    ("Find the plant around the corner", ["plant"], ["corner"], ["near:plant>corner"], []),
    ("Find the cup close to the kettle", ["cup"], ["kettle"], ["near:cup>kettle"], []),
    ("Take the metal spoon from the wooden tray", ["metal spoon"], ["wooden tray"], ["on:metal spoon>wooden tray"], []),
    ("Identify the trash can closest to the desk", ["trash can"], ["desk"], ["near:trash can>desk"], []),
    ("Pick up three apples", ["apple"], [], [], []),
    ("Find a bench", ["bench"], [], [], []),
    ("Go to the table and grab the phone", ["table", "phone"], [], [], []),
    ("Find the mice and keyboards", ["mouse", "keyboard"], [], [], []),
    ("Could you please locate the fire extinguishers?", ["fire extinguisher"], [], [], []),
    ("Avoid obstacles", ["obstacle"], [], [], []),
    ("Find the leaves on the ground", ["leaf"], ["ground"], ["on:leaf>ground"], []),
    ("Scan the room for people", ["person"], [], [], []),
    ("Look at the clock on the wall", ["clock"], ["wall"], ["on:clock>wall"], []),
    ("Pick up the cup that is on the table", ["cup"], ["table"], ["on:cup>table"], []),
    ("Find the cup that I left on the table", ["cup"], ["table"], ["on:cup>table"], []),
    ("Approach the red door without hitting the boxes", ["red door", "box"], [], [], []),
    ("Where are my keys?", ["key"], [], [], []),
    ("Is there a cup on the table?", ["cup"], ["table"], ["on:cup>table"], []),
    ("Fetch the t-shirt from the bed", ["t-shirt"], ["bed"], ["on:t-shirt>bed"], []),
    ("Find the batteries next to the flashlight", ["battery"], ["flashlight"], ["near:battery>flashlight"], []),
    ("Grab the glass of water on the counter", ["glass of water"], ["counter"], ["on:glass of water>counter"], []),
    ("Navigate to the door, avoiding the wet floor", ["door", "wet floor"], [], [], []),
    ("Head over to the couch", ["couch"], [], [], []),
    ("Pick up the box on the edge of the table", ["box"], ["table"], ["on:box>table"], []),
    ("I need you to find the benches", ["bench"], [], [], []),
    ("Help me find my glasses", ["glass"], [], [], []),
    ("Can you map the bookshelves near the window", ["bookshelf"], ["window"], ["near:bookshelf>window"], []),
    ("Kindly inspect the brass lamps", ["brass lamp"], [], [], []),
    ("Locate the mugs, the bowls and the spoons", ["mug", "bowl", "spoon"], [], [], []),
    ("the red cup on the table", ["red cup"], ["table"], ["on:red cup>table"], []),
    ("Look for the keys and then go to the door", ["key", "door"], [], [], []),
    ("Find the cup on the table near the window", ["cup"], ["table", "window"], ["on:cup>table", "near:cup>window"], []),
    ("Move the chair away from the table", ["chair", "table"], [], [], []),
    ("Grab any knife sitting on top of the cutting board", ["knife"], ["cutting board"], ["on:knife>cutting board"], []),
    ("Check the potted plants in the scene", ["potted plant"], [], [], []),
    ("Explore the area and locate the boxes", ["box"], [], [], []),
    ("Find a way to the exit while avoiding the glass tables", ["exit", "glass table"], [], [], []),
    ("Retrieve the mice from the shelves", ["mouse"], ["shelf"], ["on:mouse>shelf"], []),
]


def test_extra_phrasings_count():
    assert len(EXTRA) >= 40


@pytest.mark.parametrize("text,targets,anchors,rels,unsup", EXTRA, ids=[e[0][:40] for e in EXTRA])
def test_extra_phrasings(text, targets, anchors, rels, unsup):
    g = P.parse(text)
    assert set(g.targets) == set(targets), g.graph_dict()
    assert set(g.anchors) == set(anchors), g.graph_dict()
    assert set(g.relations) == _rels(*rels), g.graph_dict()
    assert set(g.unsupported) == set(unsup), g.graph_dict()
    assert g.validate() == []
    assert g.backend == "rules"


def test_negation_is_dropped_with_warning():
    g = P.parse("Find the cup but not the plates")
    assert g.targets == ["cup"]
    assert any("plate" in w for w in g.warnings)


@pytest.mark.parametrize("word,singular", [
    ("shelves", "shelf"), ("boxes", "box"), ("glasses", "glass"), ("benches", "bench"), ("knives", "knife"),
    ("people", "person"), ("mice", "mouse"), ("keys", "key"), ("batteries", "battery"), ("dishes", "dish"),
    ("cups", "cup"), ("glass", "glass"), ("bus", "bus"), ("lens", "lens"), ("dirt", "dirt"), ("vases", "vase"),
    ("potatoes", "potato"), ("shoes", "shoe"), ("leaves", "leaf"), ("children", "child"), ("firemen", "fireman"),
])
def test_singularize(word, singular):
    assert singularize_word(word) == singular


def test_normalize_text():
    assert normalize_text("  Pick UP the Box!! ") == "pick up the box"
    assert normalize_text("Avoid the trash cans/dirt.") == "avoid the trash cans / dirt"
    assert normalize_text("Grab the cup. Then go") == "grab the cup , then go"
    assert normalize_text("Let's find John's mug") == "let us find john mug"
    assert normalize_text("?!...") == ""


@pytest.mark.parametrize("text", ["", "   ", "!!!???", "123 456", "...,,,///"])
def test_empty_and_garbage(text):
    g = P.parse(text)
    assert g.targets == [] and g.anchors == [] and g.relations == []
    assert g.warnings


def test_nonsense_words_warn():
    g = P.parse("asdf qwerty")
    assert g.warnings and "no verb" in g.warnings[0]


def test_type_error():
    with pytest.raises(TypeError):
        P.parse(None)  # type: ignore[arg-type]


_WORDS = ["the", "a", "cup", "cups", "on", "near", "next", "to", "under", "and", "or", "/", "find", "pick", "up",
          "table", "while", "avoiding", "in", "scene", "left", "of", "between", "that", "is", "red", "shelves",
          "please", "go", "then", ",", "not", "path", "from", "off", "closest", "by", "at", "all"]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.sampled_from(_WORDS), max_size=18).map(" ".join) | st.text(max_size=80))
def test_property_valid_and_grounded(text):
    g = P.parse(text)
    assert g.validate() == []
    vocab = text_vocabulary(text)
    for phrase in g.targets + g.anchors:
        assert is_grounded(phrase, vocab), (text, phrase)
        assert phrase == phrase.lower().strip() and phrase
    for r in g.relations:
        assert r.predicate in ("near", "on")
