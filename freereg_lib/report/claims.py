"""Directions and descriptions in prose, checked against what the run printed.

:mod:`freereg_lib.report.prose` keeps hand-typed numbers out of a notebook's Markdown. A sentence
can contradict its run without a number: "the sky stays empty" beside a printed
``fill_in_multiscale: 100.0% of pixels have depth``, "Kabsch's recall falls as the depth error
grows" beside a recall of 33, 33, 33, 67, 0 %. This module makes such a sentence checkable:

* the run prints a **check line**, a claim computed on its own outputs, with :func:`check_line`::

      check: fill_in_multiscale: the sky above the topmost ring stays empty: no (100.0% of its pixels have depth)

  the answer is ``yes``, ``no`` or ``not shown (<why>)`` (the data cannot tell, e.g. both values 0);
* a **claim** in Markdown is a clause with a word of :data:`FAMILIES` (above / below / level with,
  empty, falls / grows, agree, plausible, the right object / place, loses): it is *about* a check
  when the words before it share the check's subject (Kabsch, recall, sky, peak, ...), the best
  match winning; names of rival things (diffusion / geometric / fused, Kabsch / PnP, the two
  densifiers) must not disagree;
* a claim that asserts what its check answers ``no`` to, or denies what it answers ``yes`` to, or
  asserts what the run could not show, is **contradicted**: :func:`judgements` reads each claim
  against its check, :func:`contradictions` keeps the contradicted ones.

A sentence phrased as what to look for or as the paper's reading ("should", "whether", "if", "the
paper", "expect") states no result of the run and is not read. A claim no check line is about is not
judged here: a description of a figure is written as what to look for, or backed by a check line.

:func:`printed_verdicts` reads the other way: every printed line that carries a verdict of
:mod:`freereg_lib.report.vocabulary` must have the vocabulary's form and the verdict its own numbers
give (no "holds" on 0 against 0, on fewer than ``MIN_PAIRS`` pairs, or without a significant p).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from freereg_lib.report.vocabulary import verdict


def check_line(claim: str, ok: bool | None, evidence: str, why_not: str = "") -> str:
    """``check: <claim>: yes|no (<evidence>)``; ``ok=None``: ``not shown (<why_not>; <evidence>)``."""
    answer = "yes" if ok else "no" if ok is not None else f"not shown ({why_not}"
    return f"check: {claim}: {answer}" + (f"; {evidence})" if ok is None else f" ({evidence})")


def falls(values: Sequence[float]) -> bool:
    """Falls along the sequence: never up from one step to the next, and lower at the end."""
    v = np.asarray(values, dtype=float)
    return bool(len(v) > 1 and np.all(np.diff(v) <= 0) and v[-1] < v[0])


def grows(values: Sequence[float]) -> bool:
    """Grows along the sequence: never down from one step to the next, and higher at the end."""
    return falls(-np.asarray(values, dtype=float))


def series(values: Iterable[float], fmt: str = ".0f") -> str:
    """``33, 33, 67, 0``: a printed sequence for a check's evidence."""
    return ", ".join(format(float(x), fmt) for x in values)


def colour_agreement(desc_image: np.ndarray, desc_depth: np.ndarray, rows_image: np.ndarray,
                     rows_depth: np.ndarray, seed: int = 0) -> float:
    """How far apart true partners' PCA colours are (:func:`freereg_lib.report.plots.keypoint_colours`,
    the colours of the feature pictures), as a multiple of how far apart random image / depth keypoints'
    colours are: median distance of the ``(rows_image[k], rows_depth[k])`` pairs over the median of as many
    random pairs. Near 0: the colours agree across the two sides; near 1: they carry nothing across."""
    from freereg_lib.report.plots import keypoint_colours

    colours, _ = keypoint_colours(desc_image, desc_depth)
    img, dep = colours[:len(desc_image)], colours[len(desc_image):]
    true = np.linalg.norm(img[rows_image] - dep[rows_depth], axis=1)
    rng = np.random.default_rng(seed)
    k = max(len(rows_image), 200)
    rand = np.linalg.norm(img[rng.integers(len(img), size=k)] - dep[rng.integers(len(dep), size=k)], axis=1)
    return float(np.median(true) / max(np.median(rand), 1e-9))


def border_px(uv: Sequence[float], size_hw: Sequence[int]) -> float:
    """A pixel's distance to the nearest border of an image of size ``(H, W)``."""
    (u, v), (h, w) = uv, size_hw[:2]
    return float(min(u, v, w - 1 - u, h - 1 - v))


# A claim's word families: the key is the canonical word, the pattern the ways prose writes it.
# "above"/"below" as a preposition ("above the topmost ring") are places, not comparisons.
_NOT_A_COMPARISON = r"(?!\s+(?:the|a|an|its|their|this|that|these|those|each|every|all|it|them)\b)"
FAMILIES: dict[str, str] = {
    "above": r"\b(?:above|higher than|beats?|outperforms?)\b" + _NOT_A_COMPARISON,
    "below": r"\b(?:below|lower than)\b" + _NOT_A_COMPARISON,
    "level": r"\b(?:level with|on par with|ties with)\b",
    "empty": r"\b(?:empty|unfilled)\b",
    "falls": r"\b(?:falls?|fell|falling|drops?|dropping|decreases?|declines?)\b"
             r"(?!\s+(?:inside|within|into|outside|behind|on|onto|in|out|back)\b)",  # "falls inside": a place
    "grows": r"\b(?:grows?|grew|growing|rises?|rose|rising|increases?)\b",
    "agree": r"\b(?:agrees?|agreeing)\b",
    "plausible": r"\b(?:im)?plausible\b",
    "right": r"\b(?:right|correct)\s+(?:\*?(?:object|objects|place|spot|region|partner)\b\*?)",
    "loses": r"\b(?:loses?|lost|losing)\b",
}
_FAMILY = re.compile("|".join(f"(?P<{k}>{v})" for k, v in FAMILIES.items()), re.I)
# Rival names: a claim about one of them is not about a check on another.
RIVALS = ("diffusion", "geometric", "fused", "kabsch", "pnp", "raw", "fill_in_fast", "fill_in_multiscale")
_HEDGE = re.compile(r"\b(?:should|would|could|may|might|whether|if|expects?|expected|paper|paper's|"
                    r"suppose|supposed|ideally)\b|\?", re.I)
_NEGATION = re.compile(r"\b(?:not|no|never|neither|nor|none|without|cannot|hardly)\b|n't\b", re.I)
# "as the depth error grows", "when no candidate is plausible", "where both agree": the condition, not the claim.
_CONDITION = re.compile(r"\b(?:as|when|while|once|until|unless|where)\b[^,;]*$", re.I)
_STOP = set("""the a an of to in on at by for from and or but so as is are be been was were it its their this
that these those with into than then there here each every all one two only what which who how also more
most less least very much many any some such both either over under per via just than yet do does did
has have had""".split())
_SYNONYMS = {"recall": "rr", "colors": "colour", "color": "colour", "colours": "colour", "errors": "error",
             "matched": "matches", "match": "matches"}
_CHECK = re.compile(r"^\s*check: (?P<claim>.+): (?P<answer>yes|no|not shown)\b(?: ?\((?P<evidence>.*)\))?\s*$")


@dataclass(frozen=True)
class Check:
    """One printed check line: the claim, its answer (True, False or None: not shown) and evidence."""

    claim: str
    ok: bool | None
    evidence: str = ""


def _words(text: str) -> set[str]:
    """A text's content words: lower case, plural 's' dropped, synonyms folded, claim words and stop words out."""
    text = _FAMILY.sub(" ", text.replace("`", " ").replace("*", " ").lower())
    out = set()
    for w in re.findall(r"[a-z][a-z0-9_'-]+", text):
        w = _SYNONYMS.get(w, w.removesuffix("'s"))
        if len(w) > 3 and w.endswith("s") and not w.endswith("ss") and w not in RIVALS:
            w = w[:-1]
        if w not in _STOP and len(w) > 1:
            out.add(_SYNONYMS.get(w, w))
    return out


def _claims(text: str) -> Iterable[tuple[str, str, str, str, str]]:
    """``(family, words as written, the words before them in their clause, the sentence up to them, the
    clause)`` for each claim word of a sentence."""
    at = 0
    for clause in re.split(r"([,;:()\[\]—]|\s-\s|\bbut\b|\bwhereas\b)", text):
        start = 0
        for m in _FAMILY.finditer(clause):
            yield m.lastgroup, m.group(), clause[start:m.start()], text[:at + m.start()], clause
            start = m.end()
        at += len(clause)


def printed_checks(nb: Mapping[str, Any]) -> list[Check]:
    """The check lines a run printed (stdout and plain-text results of its code cells), in order."""
    found = []
    for text in _printed(nb):
        for line in text.splitlines():
            m = _CHECK.match(line)
            if m:
                ok = {"yes": True, "no": False}.get(m.group("answer"))
                found.append(Check(m.group("claim"), ok, (m.group("evidence") or "").strip()))
    return found


def _printed(nb: Mapping[str, Any]) -> Iterable[str]:
    for cell in nb.get("cells", []):
        if cell.get("cell_type") != "code":
            continue
        for out in cell.get("outputs", []):
            text = out.get("text") if out.get("output_type") == "stream" and out.get("name") == "stdout" \
                else (out.get("data") or {}).get("text/plain")
            if text:
                yield text if isinstance(text, str) else "".join(text)


def _about(family: str, before: str, prefix: str, sentence: str, checks: Sequence[Check]) -> list[Check]:
    """The checks a claim is about: same claim word, a subject shared with the words before the claim word
    (in its clause, else in its sentence), no rival named differently; the best matches."""
    near, whole = _words(before) or _words(prefix), _words(sentence)
    scored = []
    for c in checks:
        head = next((m for m in _FAMILY.finditer(c.claim)), None)
        if head is None or head.lastgroup != family:
            continue
        subject = _words(c.claim)
        named = {r for r in RIVALS if r in subject}
        rival = {r for r in RIVALS if r in near} or {r for r in RIVALS if r in whole}
        if named and rival and not named & rival:
            continue
        if not near & subject:
            continue
        scored.append((10 * len(near & subject) + len(whole & subject), c))
    best = max((s for s, _ in scored), default=0)
    return [c for s, c in scored if s == best]


@dataclass(frozen=True)
class Judgement:
    """A Markdown clause read against the printed check it is about: asserted or denied, and whether the
    check contradicts it (it asserts what the check denies, denies what it confirms, or asserts what the
    run could not show)."""

    words: str     # the clause's claim word, as written
    clause: str
    asserted: bool
    check: Check

    @property
    def contradicted(self) -> bool:
        return self.check.ok is None and self.asserted or self.check.ok is not None and self.check.ok != self.asserted

    def __str__(self) -> str:
        says = {True: "yes", False: "no", None: "not shown"}[self.check.ok]
        return (f"{self.words!r} in {' '.join(self.clause.split())!r}: the run's check {self.check.claim!r} says "
                f"{says} ({self.check.evidence})")


def judgements(markdown: str, checks: Sequence[Check]) -> list[Judgement]:
    """Each claim of ``markdown`` that a printed check is about, read against it (its best match first).
    Code blocks, math, and sentences phrased as what to look for or as the paper's reading are not read."""
    text = re.sub(r"```.*?```|\$\$.+?\$\$|\$[^$\n]+\$", " ", markdown, flags=re.S)
    text = re.sub(r"`([^`]*)`", lambda m: m.group(1) if re.fullmatch(r"[\w.]+", m.group(1)) else " ", text)
    found = []
    for sentence in re.split(r"(?<=[.!?])\s+|\n\s*\n", text):
        if _HEDGE.search(sentence):
            continue
        for family, words, before, prefix, clause in _claims(sentence):
            if _CONDITION.search(before):
                continue
            asserted = not _NEGATION.search(before) and not words.lower().startswith("im")
            found += [Judgement(words, clause, asserted, c) for c in _about(family, before, prefix, sentence, checks)]
    return found


def contradictions(markdown: str, checks: Sequence[Check]) -> list[Judgement]:
    """The claims of ``markdown`` its printed checks contradict, one per sentence and check."""
    out, seen = [], set()
    for j in judgements(markdown, checks):
        if j.contradicted and (j.clause, j.check) not in seen:
            seen.add((j.clause, j.check))
            out.append(j)
    return out


# A verdict line of the vocabulary: "<claim>: <verdict>: <a> vs <b>, <diff> <unit>, <p>; n = <n> pairs, ...".
_VERDICT = re.compile(r"(?P<word>holds|does not hold|same direction, not significant|"
                      r"opposite direction, (?:not )?significant|no difference|cannot be told(?: \([^)]*\))?)")
_LINE = re.compile(r"^(?P<claim>.+?): " + _VERDICT.pattern + r": (?P<a>.*?) (?P<va>-?\d+(?:\.\d+)?|nan)"
                   r"(?: \[[^\]]*\])? vs (?P<b>.*?) (?P<vb>-?\d+(?:\.\d+)?|nan)(?: \[[^\]]*\])?, "
                   r"(?P<diff>[+-]\d+(?:\.\d+)?) \w+, (?P<p>p [<=] \d+(?:\.\d+)?|no p); n = (?P<n>\d+) pairs")


def verdict_problem(line: str) -> str | None:
    """Why a printed line's verdict is not the vocabulary's verdict for its own numbers (None: it is, or
    the line carries no verdict). Lines that name a verdict word after a claim's colon must parse."""
    found = re.search(r":\s*" + _VERDICT.pattern + r"(?=\s*(?:$|[:(,;]))", line)
    if not found:
        return None
    m = _LINE.match(line.strip())
    if not m:
        return f"a verdict ({found.group('word')!r}) not in the vocabulary's form (freereg_lib.report.vocabulary)"
    word, n, diff = m.group("word"), int(m.group("n")), float(m.group("diff"))
    p = None if m.group("p") == "no p" else float(m.group("p").split()[-1])
    # The direction the paper claims, as the word implies it; then the vocabulary's verdict on the numbers.
    sign = (1 if diff >= 0 else -1) * (-1 if word.startswith("opposite") else 1)
    both_zero = float(m.group("va")) == 0 and float(m.group("vb")) == 0
    expected = verdict(diff, p, n, sign, both_zero)
    if expected.split(" (")[0] == word.split(" (")[0] or abs(diff) < 0.05 and expected == "no difference":
        return None  # a difference printed as +0.0 may be a small one: its verdict stands
    return f"{word!r} where the vocabulary gives {expected!r} on these numbers"


def printed_verdicts(nb: Mapping[str, Any]) -> list[tuple[str, str]]:
    """``(line, problem)`` for each printed line whose verdict is not what the vocabulary gives its numbers."""
    return [(line.strip(), why) for text in _printed(nb) for line in text.splitlines()
            if (why := verdict_problem(line))]
