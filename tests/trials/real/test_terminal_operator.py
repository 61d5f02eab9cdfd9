"""The one-key terminal UI on a real pseudo-terminal: keys typed during the policy loop reach the
next poll, stale keys cannot answer a prompt, and a closed terminal is an end of input."""

from __future__ import annotations

import io
import os
import threading
import time
import types

import pytest

from trials.real.operator import Decision, TerminalOperator


@pytest.fixture
def term():
    """``(operator, type_keys, close)``: a TerminalOperator reading the slave side of a pty."""
    master, slave = os.openpty()
    stdin = os.fdopen(slave, "r")
    out = io.StringIO()
    closed = []

    def type_keys(keys: bytes, after: str | None = None, times: int = 1, timeout_s: float = 10.0):
        """Type ``keys`` now, or (in a thread) once ``after`` has been shown ``times`` times."""
        if after is None:
            os.write(master, keys)
            return None

        def later():
            t0 = time.monotonic()
            while out.getvalue().count(after) < times:
                if time.monotonic() - t0 > timeout_s:
                    return
                time.sleep(0.005)
            os.write(master, keys)

        th = threading.Thread(target=later, daemon=True)
        th.start()
        return th

    def close():
        os.close(master)
        closed.append(True)

    op = TerminalOperator(stdin=stdin, stdout=out)
    yield op, type_keys, close, out
    if not closed:
        os.close(master)
    stdin.close()


def _poll_until(op, timeout_s: float = 5.0):
    """Poll as the policy loop does (every few ms) until a command arrives."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        cmd = op.poll()
        if cmd is not None:
            return cmd
        time.sleep(0.01)
    return None


def test_the_operator_sees_a_terminal(term):
    op, *_ = term
    assert op.tty


def test_a_key_typed_between_two_polls_pauses_or_aborts(term):
    op, type_keys, _, _ = term
    assert op.poll() is None
    type_keys(b"p")  # typed while the loop was rendering or waiting for the policy, not inside poll()
    time.sleep(0.05)
    assert _poll_until(op) == "pause"
    type_keys(b"x")  # other keys are no command
    time.sleep(0.05)
    assert op.poll() is None
    type_keys(b"q")
    assert _poll_until(op) == "abort"


def test_a_stale_enter_cannot_accept_an_outcome_and_an_override_is_confirmed(term):
    op, type_keys, _, out = term
    type_keys(b"\r")  # pressed during the policy loop
    time.sleep(0.05)
    th = type_keys(b"a", after="[enter/y] accept")
    th2 = type_keys(b"\r", after="outcome: adversarial")
    d = op.confirm(None, types.SimpleNamespace(reached="goal"), "auto: goal")
    th.join(1), th2.join(1)
    assert d == Decision("adversarial", "")
    assert "outcome: adversarial (override)" in out.getvalue()


def test_a_note_is_read_as_a_line(term):
    op, type_keys, _, _ = term
    type_keys(b"t", after="[enter/y] accept")
    type_keys(b"cable moved\n", after="note: ")
    t3 = type_keys(b"y", after="[enter/y] accept", times=2)  # the prompt again, after the note
    d = op.confirm(None, types.SimpleNamespace(reached="goal"), "auto: goal")
    t3.join(1)
    assert d.outcome is None and d.note == "cable moved" and not d.abort


def test_placement_skip_and_resume_after_pause(term):
    op, type_keys, _, _ = term
    type_keys(b"s", after="[s] skip")
    assert op.placement(None, [], 1) == "skip"
    type_keys(b"p")  # the pause key itself must not also resume
    time.sleep(0.05)
    th = type_keys(b"k", after="paused:")
    assert op.paused() == "resume"
    th.join(1)


def test_a_closed_terminal_is_an_end_of_input(term):
    op, _, close, _ = term
    close()
    with pytest.raises(EOFError, match="operator input closed"):
        op.placement(None, [], 1)


def test_back_after_a_wrong_override_key_lets_the_operator_choose_again(term):
    op, type_keys, _, out = term
    type_keys(b"n", after="[enter/y] accept")  # the wrong key
    type_keys(b"b", after="outcome: none (override)")
    type_keys(b"a", after="[enter/y] accept", times=2)
    th = type_keys(b"\r", after="outcome: adversarial (override)")
    d = op.confirm(None, types.SimpleNamespace(reached="goal"), "auto: goal")
    th.join(1)
    assert d == Decision("adversarial", "") and "back: outcome goal (automatic)" in out.getvalue()


def test_q_aborts_at_the_override_confirmation_too(term):
    op, type_keys, _, _ = term
    type_keys(b"a", after="[enter/y] accept")
    th = type_keys(b"q", after="outcome: adversarial")
    d = op.confirm(None, types.SimpleNamespace(reached="goal"), "auto: goal")
    th.join(1)
    assert d.abort


def test_a_key_that_means_nothing_is_answered_with_the_keys_that_do(term):
    op, type_keys, _, out = term
    type_keys(b"z", after="[enter/y] accept")
    th = type_keys(b"y", after="does nothing here")
    d = op.confirm(None, types.SimpleNamespace(reached="goal"), "auto: goal")
    th.join(1)
    assert d == Decision() and "'z' does nothing here: [enter/y] accept" in out.getvalue()


def test_while_the_policy_runs_keys_do_not_echo_and_a_status_line_shows_them(term):
    import termios

    op, type_keys, _, out = term
    with op.running():
        assert "running: [p] pause   [q] abort" in out.getvalue()
        assert not termios.tcgetattr(op.stdin.fileno())[3] & termios.ECHO  # held for the whole loop
        type_keys(b"x")
        time.sleep(0.05)
        assert op.poll() is None and "'x' does nothing while the policy runs" in out.getvalue()
        type_keys(b"p")
        time.sleep(0.05)
        assert _poll_until(op) == "pause"
    assert termios.tcgetattr(op.stdin.fileno())[3] & termios.ECHO  # restored after the loop
