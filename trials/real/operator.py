"""The operator's side of a trial session: prompts, single-key answers, and scripted stand-ins.

The runner asks an :class:`Operator` four things: what to do about a failed placement check,
whether to pause or abort during the policy loop (:meth:`poll`, never blocking), when to go on
after a pause, and whether the automatic outcome stands (with an optional note).

* :class:`TerminalOperator`: one key per action, read in cbreak mode on a TTY (plain line input
  otherwise, e.g. through a pipe). Keys:

  ============  ==========================================================
  enter / y     accept the automatic outcome
  g a n u       override the outcome: goal / adversarial / none / unknown
  b             back: re-choose (after an override key, before enter)
  t             type a note for this trial (ends with enter)
  r             re-check the placement
  s             skip the placement check for this trial (logged)
  p             pause (the arm stops); any key but q resumes
  q             abort, at every prompt and during the loop: stop the arm, drop the trial in progress, exit
  ============  ==========================================================

  A key that means nothing at a prompt is answered with the keys that do. While the policy runs,
  a status line shows ``[p] pause  [q] abort`` and the terminal stays in cbreak mode without echo
  (:meth:`TerminalOperator.running`), so a key typed between two polls neither echoes nor is lost.
  A committed trial is corrected afterwards with ``advobj trial amend`` (the old value is kept).

  Closed input (end of file on stdin) raises :class:`EOFError`, which the runner handles as ``q``.

* :class:`AutoOperator`: accepts every outcome (``--auto-confirm``, CI).
* :class:`ScriptedOperator`: answers from a YAML file (``--answers``): either a mapping
  ``{trial_id: {outcome: adversarial, note: "..."}}`` or a list of such entries, entry ``i`` for
  the ``i``-th trial of the plan's run order (by position, not by how many trials this run has
  done, so a resumed session reads the same answers as an uninterrupted one); ``outcome: accept``
  (or no outcome) keeps the automatic one. Trials without an answer keep theirs.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import sys
import termios
import tty
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from sim.configio import file_error, read_yaml
from sim.errors import AdvobjError

__all__ = [
    "OUTCOMES",
    "Decision",
    "Operator",
    "AutoOperator",
    "ScriptedOperator",
    "TerminalOperator",
    "AnswersError",
    "load_answers",
]

OUTCOMES = ("goal", "adversarial", "none", "unknown")
_OVERRIDE_KEYS = {"g": "goal", "a": "adversarial", "n": "none", "u": "unknown"}


class AnswersError(AdvobjError, ValueError):
    """A scripted answers file is malformed; the message names the file and entry."""


@dataclass(frozen=True)
class Decision:
    """The operator's verdict on one trial: ``outcome`` None = the automatic outcome stands."""

    outcome: str | None = None
    note: str = ""
    abort: bool = False


class Operator(Protocol):
    def show(self, text: str) -> None: ...

    def placement(self, trial, issues, attempt: int) -> str:
        """``"recheck"``, ``"skip"`` or ``"abort"`` after a failed placement check."""

    def poll(self) -> str | None:
        """Non-blocking: ``"pause"``, ``"abort"`` or None (called every control step)."""

    def paused(self) -> str:
        """Block until the operator resumes (``"resume"``) or aborts (``"abort"``)."""

    def confirm(self, trial, result, info: str) -> Decision: ...


class AutoOperator:
    """Accepts everything; a failed placement check is re-checked a few times, then aborts.

    Without a simulated stage nobody will move the objects, so endless re-checks would hang a
    scripted session: ``max_rechecks`` bounds them.
    """

    def __init__(self, log=print, max_rechecks: int = 3):
        self.log = log
        self.max_rechecks = max_rechecks

    def show(self, text: str) -> None:
        if self.log is not None:
            self.log(text)

    def placement(self, trial, issues, attempt: int) -> str:
        return "recheck" if attempt < self.max_rechecks else "abort"

    def poll(self) -> str | None:
        return None

    def paused(self) -> str:
        return "resume"

    def confirm(self, trial, result, info: str) -> Decision:
        return Decision()


def load_answers(path: str | Path):
    """``{trial_id: Decision}`` or ``[Decision, ...]`` from an answers YAML (errors name the entry)."""
    p = Path(path)
    data = read_yaml(p, "answers file", error=file_error(AnswersError), mapping=False)

    def entry(where: str, v) -> Decision:
        if isinstance(v, str):
            v = {"outcome": v}
        if not isinstance(v, dict):
            raise AnswersError(f"{p}: {where}: expected {{outcome: ..., note: ...}} or an outcome name, got {v!r}")
        unknown = set(v) - {"outcome", "note"}
        if unknown:
            raise AnswersError(f"{p}: {where}: unknown keys {sorted(unknown)} (allowed: outcome, note)")
        out = v.get("outcome", "accept")
        if out not in (*OUTCOMES, "accept"):
            raise AnswersError(f"{p}: {where}.outcome: {out!r} is not one of accept, {', '.join(OUTCOMES)}")
        note = v.get("note", "")
        if not isinstance(note, str):
            raise AnswersError(f"{p}: {where}.note: must be text")
        return Decision(None if out == "accept" else out, note)

    if isinstance(data, dict):
        return {str(k): entry(str(k), v) for k, v in data.items()}
    if isinstance(data, list):
        return [entry(f"entry {i}", v) for i, v in enumerate(data)]
    raise AnswersError(f"{p}: expected a mapping trial_id -> answer or a list of answers, got {type(data).__name__}")


class ScriptedOperator(AutoOperator):
    """:class:`AutoOperator` whose outcome decisions come from an answers file."""

    def __init__(self, answers, log=print, source: str = "answers"):
        super().__init__(log)
        self.answers = answers
        self.source = source
        self._position: dict[str, int] | None = None  # trial id -> position in the run order (check_plan)

    @classmethod
    def from_file(cls, path, log=print) -> "ScriptedOperator":
        return cls(load_answers(path), log, str(path))

    def check_plan(self, plan) -> None:
        """Refuse answers the plan has no trial for (a typo or a list for another plan would be silently ignored)."""
        if isinstance(self.answers, dict):
            ids = {t.trial_id for t in plan.trials}
            bad = sorted(set(self.answers) - ids)
            if bad:
                raise AnswersError(
                    f"{self.source}: trial ids not in the plan: {', '.join(bad[:5])}" + (" ..." if len(bad) > 5 else "")
                )
            return
        if len(self.answers) > len(plan.trials):
            raise AnswersError(
                f"{self.source}: {len(self.answers)} answers for a plan of {len(plan.trials)} trials "
                "(entry i answers the i-th trial of the run order)"
            )
        self._position = {t.trial_id: i for i, t in enumerate(sorted(plan.trials, key=lambda t: t.order))}

    def confirm(self, trial, result, info: str) -> Decision:
        if isinstance(self.answers, dict):
            return self.answers.get(trial.trial_id, Decision())
        # entry i = the i-th trial of the run order; without check_plan, a generated plan's order is that position
        i = trial.order if self._position is None else self._position[trial.trial_id]
        return self.answers[i] if i < len(self.answers) else Decision()


class TerminalOperator:
    """Single-key terminal UI (see the module docstring for the keys)."""

    def __init__(self, stdin=None, stdout=None):
        self.stdin = stdin or sys.stdin
        self.stdout = stdout or sys.stdout
        self.tty = self.stdin.isatty()

    # ------------------------------------------------------------------ io
    def show(self, text: str) -> None:
        print(text, file=self.stdout, flush=True)

    @contextlib.contextmanager
    def _cbreak(self):
        if not self.tty:
            yield
            return

        fd = self.stdin.fileno()
        try:
            old = termios.tcgetattr(fd)
        except termios.error as err:
            if err.args and err.args[0] == errno.EIO:  # the terminal is gone
                raise EOFError("operator input closed") from None
            raise
        try:
            # TCSANOW, not tty's default TCSAFLUSH: a key typed between two polls of the policy
            # loop (p, q) waits in the input queue and must still be read by the next poll.
            tty.setcbreak(fd, termios.TCSANOW)
            yield
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, old)

    def _discard_typeahead(self) -> None:
        """Drop keys typed before a prompt, so a stale enter cannot answer a question not yet shown."""
        if self.tty:
            try:
                termios.tcflush(self.stdin.fileno(), termios.TCIFLUSH)
            except termios.error as err:
                if err.args and err.args[0] == errno.EIO:  # the terminal is gone
                    raise EOFError("operator input closed") from None
                raise

    def _read_byte(self) -> bytes:
        try:
            raw = os.read(self.stdin.fileno(), 1)
        except OSError as err:  # a pty whose other end closed reads EIO, not EOF
            if err.errno == errno.EIO:
                raise EOFError("operator input closed") from None
            raise
        if raw == b"":
            raise EOFError("operator input closed")
        return raw

    @contextlib.contextmanager
    def running(self):
        """The policy loop: cbreak without echo throughout (keys wait for :meth:`poll`), a status line."""
        self.show("  running: [p] pause   [q] abort")
        with self._cbreak():
            self._held = True
            try:
                yield
            finally:
                self._held = False

    _held = False

    def _key(self, allowed: str, hint: str | None = None) -> str:
        """One key from ``allowed`` ('\\n' = enter); another key gets ``hint`` (the keys that work)."""
        while True:
            if self.tty:
                with self._cbreak():
                    raw = self._read_byte()
                ch = raw.decode(errors="ignore")
            else:
                line = self.stdin.readline()
                if line == "":
                    raise EOFError("operator input closed")
                ch = line.strip()[:1] or "\n"
            ch = "\n" if ch in ("\r", "\n") else ch.lower()
            if ch and ch in allowed:  # "" (an undecodable byte) is "in" every string
                return ch
            if hint and ch:
                self.show(f"  {'enter' if ch == chr(10) else repr(ch)} does nothing here: {hint}")

    def _line(self, prompt: str) -> str:
        self.stdout.write(prompt)
        self.stdout.flush()
        return self.stdin.readline().strip()

    # ------------------------------------------------------------------ protocol
    def placement(self, trial, issues, attempt: int) -> str:
        self._discard_typeahead()
        for i in issues:
            self.show(f"  ! {i.message}")
        keys = "[r/enter] re-check   [s] skip the check (logged)   [q] abort"
        self.show(f"  {keys}")
        return {"r": "recheck", "\n": "recheck", "s": "skip", "q": "abort"}[self._key("rsq\n", keys)]

    def poll(self) -> str | None:
        if not self.tty:
            return None
        with contextlib.nullcontext() if self._held else self._cbreak():
            ready, _, _ = select.select([self.stdin], [], [], 0)
            if not ready:
                return None
            ch = self._read_byte().decode(errors="ignore").lower()
        cmd = {"p": "pause", "q": "abort"}.get(ch)
        if cmd is None and ch.strip():
            self.show(f"  {ch!r} does nothing while the policy runs: [p] pause   [q] abort")
        return cmd

    def paused(self) -> str:
        self._discard_typeahead()  # the p itself, or keys pressed while the arm stopped, do not resume
        self.show("  paused: the arm is stopped. [any key] resume (the trial restarts)   [q] abort")
        ch = self._key("abcdefghijklmnopqrstuvwxyz \n")
        return "abort" if ch == "q" else "resume"

    def confirm(self, trial, result, info: str) -> Decision:
        note = ""
        outcome = None
        self._discard_typeahead()  # keys pressed during the policy loop must not accept this outcome
        self.show(info)
        if result.reached == "unknown":
            self.show(
                "  the camera could not tell the outcome: which object did the gripper reach? [g/a/n] say so, "
                "[enter/u] keep it unknown"
            )
        keys = "[enter/y] accept   [g/a/n/u] override: goal/adversarial/none/unknown   [t] note   [q] abort"
        then = "[enter/y] confirm   [t] note, then confirm   [b] back: choose again   [q] abort"
        while True:
            self.show(f"  {keys}")
            ch = self._key("\nygantuq", keys)
            if ch == "q":
                return Decision(abort=True)
            if ch == "t":
                note = self._line("  note: ")
                continue
            if ch in _OVERRIDE_KEYS:
                outcome = _OVERRIDE_KEYS[ch]
                if outcome == result.reached:
                    outcome = None  # the same as the automatic outcome: not an override
                self.show(f"  outcome: {outcome or result.reached}" + (" (override)" if outcome else "") + f"   {then}")
                ch = self._key("\nytbq", then)  # confirm the override (or add a note first), or go back
                if ch == "q":
                    return Decision(abort=True)
                if ch == "b":
                    outcome = None
                    self.show(f"  back: outcome {result.reached} (automatic)")
                    continue
                if ch == "t":
                    note = self._line("  note: ")
                return Decision(outcome, note)
            return Decision(outcome, note)
