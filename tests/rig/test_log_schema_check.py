"""The run log's compiled schema check (``fastjsonschema``, per document kind) against ``jsonschema``'s reading of
the whole :data:`~magctl.rig.log.SCHEMA`: the same verdict on every document of a real run and on every one-field
corruption of each kind, and a refused document's line names the field."""

from __future__ import annotations

import copy
import json

import jsonschema
import pytest

from magctl.rig.log import SCHEMA, schema_error
from magctl.rig.runtime import Runtime
from magctl.rig.sim import SimRig

WRONG = [None, "x", True, False, -1, 0, 1.5, 2.0, -0.5, 2**70, [], [1.0], [1.0, 2.0, 3.0], {}, {"a": 1}]
"""Values put in place of each field: every JSON type, signs, an integral float, a huge integer."""


@pytest.fixture(scope="module")
def documents(tmp_path_factory):
    path = tmp_path_factory.mktemp("logs") / "run.jsonl"
    Runtime(SimRig(n_spheres=2), "side-push", {}, log_path=path, realtime=False, max_ticks=40, quiet=True).run()
    docs = [json.loads(line) for line in path.read_text().splitlines()]
    by_kind = {}
    for d in docs:
        by_kind.setdefault(d["doc"], d)
    assert set(by_kind) == {"start", "descriptor", "event", "stop"}
    return docs, by_kind


def paths(doc, prefix=()):
    """Every key path of ``doc`` (dicts and lists), leaves and branches."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield (*prefix, k)
        yield from paths(v, (*prefix, k))


def corruptions(doc):
    """One change each: a field replaced by each wrong value, a field removed, an unknown field added."""
    for path in paths(doc):
        for value in WRONG:
            bad = copy.deepcopy(doc)
            node = bad
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = value
            yield bad
        if isinstance(path[-1], str):
            bad = copy.deepcopy(doc)
            node = bad
            for k in path[:-1]:
                node = node[k]
            del node[path[-1]]
            yield bad
    yield {**copy.deepcopy(doc), "unknown_field": 1}
    yield {**copy.deepcopy(doc), "doc": "nonsense"}


def test_every_document_of_a_run_passes(documents):
    docs, _ = documents
    reference = jsonschema.Draft202012Validator(SCHEMA)
    assert all(reference.is_valid(d) for d in docs)
    assert [schema_error(d) for d in docs] == [None] * len(docs)


@pytest.mark.parametrize("kind", ["start", "descriptor", "event", "stop"])
def test_the_check_and_jsonschema_agree_on_every_one_field_corruption(documents, kind):
    reference = jsonschema.Draft202012Validator(SCHEMA)
    _, by_kind = documents
    n = refused = 0
    for bad in corruptions(by_kind[kind]):
        valid = reference.is_valid(bad)
        line = schema_error(bad)
        assert (line is None) == valid, (line, json.dumps(bad)[:300])
        n += 1
        refused += line is not None
    assert n > 50 and 0 < refused < n          # the corruptions reached both verdicts


def test_a_refused_event_names_its_field(documents):
    _, by_kind = documents
    bad = copy.deepcopy(by_kind["event"])
    bad["obs"]["robot_est_m"] = [1.0]
    assert schema_error(bad) == "event document, obs.robot_est_m: [1.0] is too short"
