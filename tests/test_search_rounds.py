"""The search goes on in the slots settle frees: a search that stopped at its limit with
a candidate still carrying over runs again from the settled model once settle took a
cause out, never trying that cause again (control flow, with the search and settle
replaced by scripted rounds)."""

from __future__ import annotations

from types import SimpleNamespace

from hybrid_pk.calibration.diagnosis import search


def _model(*labels):
    return SimpleNamespace(effects=[SimpleNamespace(label=x) for x in labels])


def test_freed_slots_are_searched_and_taken_out_causes_stay_out(monkeypatch):
    pools = []
    rounds = iter(
        [  # (model after the search, its steps, model after settle, settle's steps)
            (_model("a", "b"), [{"candidate": "c", "capped": 2}], _model("a"),
             [{"candidate": "b", "removed": True}]),
            (_model("a", "d"), [], _model("a", "d"), []),
        ]
    )  # fmt: skip
    state = {}

    def fake_select(model, res, pool, *args):
        pools.append(list(pool))
        state["round"] = next(rounds)
        return state["round"][0], res, list(state["round"][1]), [], []

    def fake_settle(model, res, split, carry, steps, say):
        steps += state["round"][3]
        return state["round"][2], res, {}, []

    monkeypatch.setattr(search, "_select", fake_select)
    monkeypatch.setattr(search, "settle", fake_settle)
    tests = (0.01, SimpleNamespace(), None)
    out = search._search_settled(_model(), None, ["a", "b", "c", "d"], None, tests, 2,
                                 lambda _m: None, [])  # fmt: skip
    assert pools == [["a", "b", "c", "d"], ["c", "d"]]  # b, taken out, is not tried again
    model, _, steps = out[:3]
    assert [e.label for e in model.effects] == ["a", "d"]
    assert [s["candidate"] for s in steps] == ["c", "b"]


def test_a_search_that_stopped_by_itself_is_not_run_again(monkeypatch):
    calls = []

    def fake_select(model, res, pool, *args):
        calls.append(pool)
        return _model("a", "b"), res, [], [], []

    def fake_settle(model, res, split, carry, steps, say):
        steps.append({"candidate": "b", "removed": True})  # taken out, but no cap reached
        return _model("a"), res, {}, []

    monkeypatch.setattr(search, "_select", fake_select)
    monkeypatch.setattr(search, "settle", fake_settle)
    tests = (0.01, SimpleNamespace(), None)
    search._search_settled(_model(), None, ["a", "b"], None, tests, 2, lambda _m: None, [])
    assert len(calls) == 1
