"""A closing Zenoh sender asks its receivers whether they took its final sync
(``remote.zenoh_sender.confirm_delivery``). A query that gets no answer while a subscriber
matches must not end the wait: in CI a busy receiver's query timed out, the sender closed at
once, and the tail of the data in transit was lost. One real Zenoh session, in process."""
from __future__ import annotations

import logging
import time

import pytest

zenoh = pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")

from pointflow.remote.zenoh_sender import _matching, confirm_delivery  # noqa: E402

KEY = "pftest/confirm/src"


@pytest.fixture
def session():
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = zenoh.open(conf)
    yield s
    s.close()


def _confirm(session, pub, caplog, timeout=0.6):
    caplog.clear()
    log = logging.getLogger("test.confirm")
    with caplog.at_level(logging.INFO, logger="test.confirm"):
        confirm_delivery(session, {KEY: "src"}, timeout, log, matching=lambda k: _matching(pub))
    return [r.getMessage() for r in caplog.records]


def _until(cond, s=5.0):
    end = time.monotonic() + s
    while not cond() and time.monotonic() < end:
        time.sleep(0.02)
    return cond()


def test_no_receiver_ends_the_wait_at_once(session, caplog):
    pub = session.declare_publisher(KEY)
    assert not _matching(pub)
    assert _confirm(session, pub, caplog, timeout=30.0) == []  # (30 s would show as a hang)


def test_a_receiver_that_does_not_answer_is_waited_for_and_named(session, caplog):
    pub = session.declare_publisher(KEY)
    session.declare_subscriber(KEY, lambda sample: None)  # matched, but no queryable answers
    assert _until(lambda: _matching(pub))
    msgs = _confirm(session, pub, caplog)
    assert any("had not taken everything" in m for m in msgs), msgs


def test_pending_then_ended_is_confirmed(session, caplog):
    pub = session.declare_publisher(KEY)
    asked = []

    def answer(query):
        asked.append(1)
        query.reply(query.key_expr, b"ended" if len(asked) >= 3 else b"pending")

    session.declare_subscriber(KEY, lambda sample: None)
    session.declare_queryable(KEY, answer)
    assert _until(lambda: _matching(pub))
    msgs = _confirm(session, pub, caplog, timeout=30.0)
    assert len(asked) >= 3 and msgs == [f"1 receiver(s) of {KEY} took everything"], (asked, msgs)
