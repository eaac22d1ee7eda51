"""knowledge - recognizers and learned knowledge of a task's world model (thesis 5.4, 7).

* **recognizers** - :class:`Recognizer` maps a window of sensory history to a named pattern
  (hard-coded tests), :class:`LearnedPattern` learns the window that precedes an outcome;
* **learned responses** - :class:`Experience` correlates a pattern with the outcome of each
  response tried across runs, persisted in a JSON file beside the system's map (never in the
  source tree, a :class:`Store`) and resettable, and proposes the response that worked best.

The world model they serve is :mod:`chcos.user.worldmodel`; plans that use :class:`Experience`
are :mod:`chcos.user.plans`.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from chcos.errors import ChcosError, ConfigError

# ---- recognizers ----------------------------------------------------------------------------
Sample = tuple[float, dict[str, Any]]
"""One entry of sensory history: (time, named values)."""

PatternTest = Callable[[Sequence[Sample]], bool]


class Recognizer:
    """Maps a window of sensory history to a named pattern (hard-coded knowledge, thesis 5.4).

    ``span`` seconds (and at most ``keep`` samples) of history are kept; patterns are tests
    over that window, tried in the order they were added. :meth:`push` adds a sample and
    returns the names of the patterns the window now shows; :attr:`seen` records when each
    pattern was first recognized in the current episode (until :meth:`clear`)."""

    def __init__(self, span: float, keep: int = 1000) -> None:
        if not (span > 0 and keep > 0):
            raise ConfigError(f"Recognizer: span {span!r} and keep {keep!r}: expected > 0")
        self.span = float(span)
        self.window: deque[Sample] = deque(maxlen=keep)
        self.patterns: dict[str, PatternTest] = {}
        self.seen: dict[str, float] = {}

    def add(self, name: str, test: PatternTest) -> None:
        """Add pattern ``name``: ``test`` gets the window (oldest first) and says if it shows
        the pattern. Raises ConfigError for a name already used."""
        if name in self.patterns:
            raise ConfigError(f"Recognizer: pattern {name!r} is already defined")
        self.patterns[name] = test

    def push(self, t: float, sample: Mapping[str, Any]) -> list[str]:
        """Add ``sample`` taken at ``t``; return the patterns recognized in the window now."""
        self.window.append((float(t), dict(sample)))
        while self.window and self.window[0][0] < t - self.span:
            self.window.popleft()
        hits = [name for name, test in self.patterns.items() if test(list(self.window))]
        for name in hits:
            self.seen.setdefault(name, float(t))
        return hits

    def clear(self) -> None:
        """Forget the history and the patterns seen (a new episode)."""
        self.window.clear()
        self.seen.clear()


# ---- learned knowledge, persisted across runs ---------------------------------------------
class Store:
    """A JSON file of learned data beside the system's map (``<dir>/learned/<name>.json``),
    written atomically. Raises ConfigError when the file exists but is not valid JSON (naming
    the file), ChcosError if it cannot be written."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = Path(path) if path is not None else None

    @classmethod
    def beside(cls, directory: str | Path | None, name: str) -> Store:
        """The store ``name`` under ``directory``/learned (None: kept in memory only)."""
        if directory is None:
            return cls(None)
        return cls(Path(directory) / "learned" / f"{name}.json")

    def load(self) -> dict[str, Any]:
        """The stored document ({} if there is none)."""
        if self.path is None or not self.path.exists():
            return {}
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{self.path}: learned data unreadable: {exc}") from exc
        if not isinstance(doc, dict):
            raise ConfigError(f"{self.path}: learned data: expected a JSON object")
        return doc

    def save(self, doc: Mapping[str, Any]) -> None:
        """Write ``doc`` (atomically: a crash leaves the old file or the new one)."""
        if self.path is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=self.path.name + ".")
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(doc, f, indent=1, sort_keys=True)
            os.replace(tmp, self.path)
        except OSError as exc:
            raise ChcosError(f"{self.path}: cannot write learned data: {exc}") from exc

    def reset(self) -> None:
        """Delete the stored document."""
        if self.path is not None and self.path.exists():
            self.path.unlink()


class Experience:
    """Learned responses (thesis 5.4, 7): for each recognized ``pattern``, how often each
    ``response`` was tried and how often the task it served then succeeded - across runs, in a
    :class:`Store`. :meth:`propose` gives the response that worked best."""

    def __init__(self, store: Store) -> None:
        self.store = store
        doc = store.load()
        raw = doc.get("responses", {})
        self.table: dict[str, dict[str, list[int]]] = {
            str(p): {str(r): [int(v[0]), int(v[1])] for r, v in rs.items()}
            for p, rs in raw.items()} if isinstance(raw, dict) else {}

    def record(self, pattern: str, response: str, success: bool) -> None:
        """Note that ``response`` to ``pattern`` was followed by success or failure; saved."""
        tried = self.table.setdefault(pattern, {}).setdefault(response, [0, 0])
        tried[0] += 1
        tried[1] += bool(success)
        self.store.save({"responses": self.table})

    def rate(self, pattern: str, response: str) -> float | None:
        """Success rate of ``response`` to ``pattern`` (None if never tried)."""
        n = self.table.get(pattern, {}).get(response)
        return None if n is None or n[0] == 0 else n[1] / n[0]

    def propose(self, pattern: str, candidates: Iterable[str]) -> list[str]:
        """``candidates`` ordered best first: by success rate (Laplace-smoothed, so an untried
        response ranks as a coin toss), ties kept in the given order."""
        cands = list(candidates)

        def score(r: str) -> float:
            n = self.table.get(pattern, {}).get(r, [0, 0])
            return (n[1] + 1.0) / (n[0] + 2.0)

        return sorted(cands, key=lambda r: -score(r))

    def reset(self) -> None:
        """Forget everything learned (memory and file)."""
        self.table.clear()
        self.store.reset()


class LearnedPattern:
    """A recognizer that learns the sensory window preceding an outcome (e.g. a stuck tip).

    Each sample is a vector of named ``features``; a window (the last ``lead`` seconds) is
    summarized as the rate of change (least-squares slope) of each feature. Every full window
    :meth:`push` sees also feeds the *normal* reference: the running mean and spread of those
    rates. When the outcome happens, :meth:`learn` takes the window of the ``lead`` seconds
    before it (skipping the last ``guard`` seconds, the outcome's own onset) as an example -
    only if it differs from the normal windows (by more than ``spread`` standard deviations in
    some feature, with at least ``reference`` normal windows seen): an outcome without a
    precursor teaches nothing. :meth:`push` fires when the current window differs from normal
    and every feature's rate is within ``tolerance`` (relative) of an example's. An example
    that fires again within ``recur`` seconds of its previous alarm, with no outcome in
    between, has given a false alarm: one that has given two more false alarms than it
    predicted outcomes is forgotten (a match within ``lead`` seconds of an alarm is the same
    alarm). Examples and their scores are kept in a :class:`Store`
    across runs."""

    def __init__(self, features: Sequence[str], store: Store, *, lead: float = 1.0,
                 guard: float = 0.0, tolerance: float = 0.35, keep: int = 20,
                 spread: float = 4.0, reference: int = 20, recur: float = 2.0) -> None:
        if not features:
            raise ConfigError("LearnedPattern: expected at least one feature")
        if not (lead > 0 and guard >= 0 and tolerance > 0 and spread > 0 and reference >= 2
                and recur > 0):
            raise ConfigError(f"LearnedPattern: lead {lead!r} > 0, guard {guard!r} >= 0, "
                              f"tolerance {tolerance!r} > 0, spread {spread!r} > 0, "
                              f"reference {reference!r} >= 2, recur {recur!r} > 0 expected")
        self.features = list(features)
        self.store = store
        self.lead = float(lead)
        self.guard = float(guard)
        self.tolerance = float(tolerance)
        self.spread = float(spread)
        self.reference = int(reference)
        self.recur = float(recur)
        self.keep = keep
        doc = store.load()
        ex = doc.get("examples", [])
        self.examples: list[dict[str, float]] = [
            {str(k): float(v) for k, v in e.items()} for e in ex if isinstance(e, dict)][-keep:]
        raw = doc.get("scores", [])
        scores = [[int(x[0]), int(x[1])] for x in raw if isinstance(x, list) and len(x) == 2] \
            if isinstance(raw, list) else []
        #: [outcomes predicted, false alarms] of each example
        self.scores: list[list[int]] = (scores + [[0, 0]] * len(self.examples))[
            :len(self.examples)]
        self.history: deque[tuple[float, list[float]]] = deque()
        #: false alarms so far (every run), and examples forgotten for them
        self.false_alarms = 0
        self.forgotten = 0
        # the normal reference: count, mean and sum of squared deviations of each feature's
        # rate over the windows seen (Welford)
        self._n = 0
        self._mean = [0.0] * len(self.features)
        self._m2 = [0.0] * len(self.features)
        self._alarm: tuple[float, int] | None = None  # (time, example) of the last alarm

    def _rates(self, window: Sequence[tuple[float, list[float]]]) -> dict[str, float] | None:
        """Least-squares slope of each feature over ``window`` (robust to noisy end points)."""
        if len(window) < 3 or window[-1][0] - window[0][0] <= 0:
            return None
        n = len(window)
        tm = sum(t for t, _ in window) / n
        stt = sum((t - tm) ** 2 for t, _ in window)
        if stt <= 0:
            return None
        out: dict[str, float] = {}
        for i, f in enumerate(self.features):
            vm = sum(v[i] for _, v in window) / n
            out[f] = sum((t - tm) * (v[i] - vm) for t, v in window) / stt
        return out

    def _observe(self, rates: Mapping[str, float]) -> None:
        """Add a window's rates to the normal reference."""
        self._n += 1
        for i, f in enumerate(self.features):
            d = rates[f] - self._mean[i]
            self._mean[i] += d / self._n
            self._m2[i] += d * (rates[f] - self._mean[i])

    def differs(self, rates: Mapping[str, float]) -> bool:
        """True if ``rates`` lie outside the normal windows seen so far (more than ``spread``
        standard deviations away in some feature); False while fewer than ``reference``
        normal windows have been seen (no reference point yet)."""
        if self._n < self.reference:
            return False
        for i, f in enumerate(self.features):
            std = (self._m2[i] / (self._n - 1)) ** 0.5
            floor = 1e-3 * max(1.0, abs(self._mean[i]))  # a noise-free signal still varies
            if abs(rates[f] - self._mean[i]) > self.spread * max(std, floor):
                return True
        return False

    def push(self, t: float, sample: Mapping[str, float]) -> bool:
        """Add a sample; True if the newest ``lead`` s differ from normal and look like a
        learned precursor. Raises ConfigError if a feature is missing from ``sample``."""
        try:
            vec = [float(sample[f]) for f in self.features]
        except KeyError as exc:
            raise ConfigError(f"LearnedPattern: sample lacks feature {exc}") from exc
        self.history.append((float(t), vec))
        while self.history and self.history[0][0] < t - self.lead - self.guard - 1.0:
            self.history.popleft()
        window = [s for s in self.history if s[0] >= t - self.lead]
        if not window or window[-1][0] - window[0][0] < 0.8 * self.lead:
            return False
        rates = self._rates(window)
        if rates is None:
            return False
        if not self.differs(rates):
            self._observe(rates)  # (the reference stays normal: unusual windows stay out)
            return False
        hit = next((i for i, ex in enumerate(self.examples) if self._close(rates, ex)), None)
        if hit is None:
            return False
        last = self._alarm
        if last is not None and last[1] == hit and t - last[0] <= self.lead:
            return True  # the same alarm: its window has not been renewed yet
        if last is not None and last[1] == hit and t - last[0] <= self.recur:
            self._false_alarm(hit)
            if hit >= len(self.examples) or not self._close(rates, self.examples[hit]):
                self._alarm = None
                return False  # forgotten: no alarm from it
        self._alarm = (float(t), hit)
        return True

    def _false_alarm(self, i: int) -> None:
        """Example ``i`` fired again with no outcome since its last alarm: count it against
        the example, and forget an example with two more false alarms than predictions."""
        self.false_alarms += 1
        score = self.scores[i]
        score[1] += 1
        if score[1] >= score[0] + 2:
            del self.examples[i]
            del self.scores[i]
            self.forgotten += 1
        self._save()

    def _close(self, rates: Mapping[str, float], ex: Mapping[str, float]) -> bool:
        for f in self.features:
            a, b = rates[f], ex.get(f, 0.0)
            scale = max(abs(b), 1e-9)
            if abs(a - b) > self.tolerance * scale:
                return False
        return True

    def learn(self, t: float) -> dict[str, float] | None:
        """The outcome happened at ``t``: learn the window before it (saved), if it differs
        from the normal ones. Returns the example, or None if the history is too short or the
        window looks normal (an outcome without a precursor teaches nothing). An alarm in the
        ``recur`` seconds before counts as a prediction of its example."""
        predicted = self._alarm is not None and t - self._alarm[0] <= self.recur + self.lead
        if self._alarm is not None and predicted:
            self.scores[self._alarm[1]][0] += 1
        self._alarm = None
        end = t - self.guard
        window = [s for s in self.history if end - self.lead <= s[0] <= end]
        rates = self._rates(window)
        if rates is None or not self.differs(rates):
            if predicted:
                self._save()
            return None
        self.examples.append(rates)
        self.scores.append([0, 0])
        del self.examples[:-self.keep]
        del self.scores[:-self.keep]
        self._save()
        return rates

    def _save(self) -> None:
        self.store.save({"examples": self.examples, "scores": self.scores,
                         "features": self.features})

    def reset(self) -> None:
        """Forget every learned example (memory and file)."""
        self.examples.clear()
        self.scores.clear()
        self._alarm = None
        self.store.reset()
