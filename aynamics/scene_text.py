"""Reading scene text safely: YAML without tags, aliases or repeated keys, of bounded size and nesting, with
YAML 1.2 numbers; and the YAML inside a model's response (`<answer>`, `<think>`, fences, stray prose).

    data = load_yaml(text)           # plain Python data, or SceneError naming the line and column
    body = extract_yaml(response)    # the YAML part of a response

`scene.parse` and `scene.load` read scenes through these.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from aynamics.ranges import NO_VALUE, Problem, SceneError

MAX_TEXT_CHARS = 200_000  # a scene is a few kB; longer text is refused before parsing


# --------------------------------------------------------------------------------------------
# Safe YAML
# --------------------------------------------------------------------------------------------
class _DuplicateKey(yaml.constructor.ConstructorError):
    """A mapping repeats a key (reported as is; other constructor errors are refused tags)."""


def _core_schema_numbers(table: dict) -> dict:
    """The implicit-resolver table `table` (PyYAML's, YAML 1.1) with YAML 1.2 core-schema numbers: `1e-1` and
    `2E5` are floats (1.1 reads them as strings, then "must be a number, got str"), `1:00` is not 60 (1.1's
    base 60), `010` is 10 (1.1: octal 8; `_construct_int`), `0o17` and `0x1F` are 15 and 31; `.inf` and `.nan`
    stay floats (the fields then refuse them by name); `2024-01-01` is a string, not a date."""
    int_tag, float_tag = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
    dropped = (int_tag, float_tag, "tag:yaml.org,2002:timestamp")  # a date is a string here (then named)
    out = {k: [(tag, rx) for tag, rx in v if tag not in dropped] for k, v in table.items()}
    numbers = (
        (int_tag, re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), "-+0123456789"),
        (
            float_tag,
            re.compile(
                r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
            ),
            "-+0123456789.",
        ),
    )
    for tag, rx, first in numbers:  # integers appended first: "10" also matches the float pattern
        for ch in first:
            out.setdefault(ch, []).append((tag, rx))
    return out


def _construct_int(loader, node) -> int:
    """A YAML 1.2 integer: decimal (leading zeros included), or `0o` octal / `0x` hexadecimal."""
    text = loader.construct_scalar(node)
    body = text.lstrip("+-")
    base = {"0o": 8, "0x": 16}.get(body[:2], 10)
    value = int(body[2:] if base != 10 else body, base)
    return -value if text.startswith("-") else value


class _UniqueKeys:
    """Refuses a mapping that repeats a key (PyYAML keeps the last silently: `radius: 0.2` then `radius: 1.4` read
    as 1.4). The constructor is Python in both loaders, so the C one gets this check too."""

    def construct_mapping(self, node, deep=False):  # noqa: D102
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, str | int | float | bool):
                continue
            if key in seen:
                line = key_node.start_mark.line + 1
                msg = f"key {key!r} given twice (lines {seen[key]} and {line})"
                raise _DuplicateKey(None, None, msg, key_node.start_mark)
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


_PLAIN_TAGS = {f"tag:yaml.org,2002:{t}" for t in ("null", "bool", "int", "float", "str", "seq", "map")}


class _NoAliasLoader(_UniqueKeys, yaml.SafeLoader):
    """SafeLoader that refuses anchors/aliases (no alias bombs) and python/* tags (SafeLoader already does)."""

    yaml_implicit_resolvers = _core_schema_numbers(yaml.SafeLoader.yaml_implicit_resolvers)
    # plain YAML only: the tags !!binary, !!set, !!omap, !!pairs and !!timestamp made values no scene field takes
    # (!!set {1.0, 0.5, 0.4} became a reordered size, !!binary a name); an unknown tag is a YAML error
    yaml_constructors = {
        **{k: v for k, v in yaml.SafeLoader.yaml_constructors.items() if k in _PLAIN_TAGS or k is None},
        "tag:yaml.org,2002:int": _construct_int,
    }

    def compose_node(self, parent, index):  # noqa: D102
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.YAMLError(f"YAML aliases are not allowed (*{event.anchor} at line {event.start_mark.line + 1})")
        return super().compose_node(parent, index)


# libyaml's safe loader (PyYAML's C extension) parses a scene ~6x faster than the pure-Python one
# (benchmarks/bench_parse.py); it can't refuse aliases itself, so it only reads texts without `&` and `*`, in which
# no anchor or alias can occur. Its recursion is unbounded: ~25 000 nested `[` crash the process (segmentation
# fault) where the Python loader raises RecursionError; so it only reads texts with few characters that can open a
# level (`[`, `{`, `-`, `?`; deeper indentation alone needs more than MAX_TEXT_CHARS), a scene of ~100 objects.
_FAST_LOADER = (
    type(
        "_FastLoader",
        (_UniqueKeys, yaml.CSafeLoader),
        {
            "yaml_implicit_resolvers": _NoAliasLoader.yaml_implicit_resolvers,
            "yaml_constructors": _NoAliasLoader.yaml_constructors,
        },
    )
    if hasattr(yaml, "CSafeLoader")
    else None
)
_FAST_MAX_OPENERS = 2_000


def _loader_for(text: str) -> type:
    if _FAST_LOADER is None or "&" in text or "*" in text:
        return _NoAliasLoader
    if sum(text.count(c) for c in "[{-?") > _FAST_MAX_OPENERS:
        return _NoAliasLoader
    return _FAST_LOADER


_SURROGATE = re.compile("[\ud800-\udfff]")
# a line break as YAML (PyYAML and libyaml alike) counts them: not str.splitlines, which also breaks at \x0b, \x0c
# and \x1c-\x1e, characters YAML refuses in a scene
_BREAK = re.compile("\r\n|[\n\r\x85\u2028\u2029]")


def _line_breaks(text: str) -> int:
    return len(_BREAK.findall(text))


def _line_column(text: str, offset: int) -> str:
    """`offset` in `text` as YAML names a place: "line L, column C", both from 1."""
    last = max((m.end() for m in _BREAK.finditer(text, 0, offset)), default=0)
    return f"line {_line_breaks(text[:offset]) + 1}, column {offset - last + 1}"


def checked_text(text: str | bytes) -> str:
    """`text` as a string (bytes decoded as UTF-8), refused when binary or longer than MAX_TEXT_CHARS."""
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as e:
            raise SceneError([Problem("text", NO_VALUE, f"not UTF-8 text (byte {e.start}): binary input?")]) from None
    if "\x00" in text:
        raise SceneError([Problem("text", NO_VALUE, "contains NUL bytes: binary input?")])
    surrogate = _SURROGATE.search(text)
    if surrogate is not None:  # no UTF-8 form: the YAML reader would refuse it by its offset in the text
        where = _line_column(text, surrogate.start())
        msg = f"contains a lone surrogate character {surrogate.group()!r} ({where}): not valid Unicode text"
        raise SceneError([Problem("text", NO_VALUE, msg)])
    if len(text) > MAX_TEXT_CHARS:
        raise SceneError([Problem("text", len(text), f"too long: at most {MAX_TEXT_CHARS} characters")])
    return text


MAX_FLOW_DEPTH = 32  # levels of `[` / `{`: a scene needs 3 even in flow style, [{state: {position: [0, 0, 1]}}]
_BRACKET = re.compile(r"[\[\]{}]")


def _too_deep(text: str) -> Problem | None:
    """A problem when `[` / `{` nest more than MAX_FLOW_DEPTH levels, else None. PyYAML's Python scanner keeps
    one possible key per open flow level and walks them all at every token: 2 001 nested `[` (4 kB, a model's
    repetition loop) took 6 s to refuse, 300 lines of 300 levels (181 kB) 18 s. Brackets in quotes and comments
    count too (never 32 deep in a scene); closers there can only hide depth, which the loaders still bound."""
    depth = 0
    for m in _BRACKET.finditer(text):
        depth = depth + 1 if m.group() in "[{" else max(depth - 1, 0)
        if depth > MAX_FLOW_DEPTH:
            msg = f"nested too deeply: more than {MAX_FLOW_DEPTH} levels of [ and {{ ({_line_column(text, m.start())})"
            return Problem("yaml", NO_VALUE, msg)
    return None


def load_yaml(text: str | bytes) -> Any:
    """Parse YAML text safely: no tags that build Python objects, no aliases, bounded size and flow nesting."""
    text = checked_text(text)
    deep = _too_deep(text)
    if deep is not None:
        raise SceneError([deep])
    try:
        return yaml.load(text, Loader=_loader_for(text))  # noqa: S506 - safe loaders only
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        if isinstance(e, yaml.reader.ReaderError) and isinstance(e.character, int):
            # a control character, located by an offset (in bytes with the C loader): by line and column instead;
            # the reader stops at the first unacceptable character, so its first occurrence is the one
            offset = text.find(chr(e.character))
            problem = f"unacceptable character #x{e.character:04x}: {e.reason}"
            where = f" ({_line_column(text, offset if offset >= 0 else e.position)})"
        if isinstance(e, yaml.constructor.ConstructorError) and problem.startswith("could not determine a constructor"):
            problem = f"refused YAML tag: {problem}"
        raise SceneError([Problem("yaml", NO_VALUE, f"{problem}{where}")]) from None
    except RecursionError:
        raise SceneError([Problem("yaml", NO_VALUE, "nested too deeply")]) from None
    except ValueError as e:  # e.g. an integer past Python's 4300-digit conversion limit
        raise SceneError([Problem("yaml", NO_VALUE, f"unreadable value: {e}")]) from None


_ANSWER = re.compile(r"<answer>(.*?)(?:</answer>|$)", re.S)
_THINK = re.compile(r"<think>.*?(?:</think>|$)", re.S)
_FENCE = re.compile(r"```(?:ya?ml)?\s*\n(.*?)(?:```|$)", re.S)
# `- type:`, or `-` alone then `type:` on the next line; not \s*: runs of blank lines made the search quadratic
_FIRST_ITEM = re.compile(r"^[ \t]*-(?:[ \t]+|[ \t]*\n[ \t]+)type[ \t]*:", re.M)
_INLINE_ITEM = re.compile(r"-[ \t]+type[ \t]*:")  # an item after other text on its line


def _strip_wrappers(text: str) -> str:
    """The last `<answer>` block (an unclosed one runs to the end), else the text without `<think>`; then a fence.
    What is left out before it is left as its line breaks, so that a YAML error names the line of the response."""
    answers = list(_ANSWER.finditer(text))
    if answers:
        body = "\n" * _line_breaks(text[: answers[-1].start(1)]) + answers[-1].group(1)
    else:
        body = _THINK.sub(lambda m: "\n" * _line_breaks(m.group()), text)
    fence = _FENCE.search(body)
    return "\n" * _line_breaks(body[: fence.start(1)]) + fence.group(1) if fence else body


def _cut_prose(body: str) -> tuple[int, str] | None:
    """Where in `body` the list starts, and the part of `body` from the first `- type:` line to the last line of
    that list; or None. A first item after other text on its line ("Scene: - type: box", a stray control
    character), followed by its indented keys, starts the list there: cut with its line, it was an object dropped
    without a word."""
    m = _FIRST_ITEM.search(body)
    start = None if m is None else m.start()
    before = body if start is None else body[:start]
    inline = None
    for inline in _INLINE_ITEM.finditer(before):  # the last one before the first line-start item
        pass
    if inline is not None:  # its own keys follow it, indented, up to the next item
        keys = [line for line in _BREAK.split(body[inline.start() : start])[1:] if line.strip()]
        # indented as the list's lines below are measured (str.lstrip): a form feed or another control character
        # before a key leaves the item in, for YAML to refuse, rather than dropping the object without a word
        if keys and keys[0][:1].isspace() and (start is None or all(line[:1].isspace() for line in keys)):
            start = inline.start()
    if start is None:
        return None
    lines = _BREAK.split(body[start:])
    indent = len(lines[0]) - len(lines[0].lstrip())
    keep = []
    for line in lines:
        stripped = line.strip()
        # list items and their indented children belong; an unindented non-item line is prose
        if stripped and (len(line) - len(line.lstrip())) <= indent and not stripped.startswith("-"):
            break
        keep.append(line)
    if indent:  # a list indented under prose ("Here is the scene:\n  - type: box"): as if written at the margin
        keep = [line[indent:] if len(line) - len(line.lstrip()) >= indent else line.lstrip() for line in keep]
    return start, "\n".join(keep)


def extract_yaml(text: str) -> str:
    """Return the YAML part of a model response.

    Takes the last `<answer>...</answer>` block when there is one, otherwise drops `<think>...</think>`;
    then the inside of a ```yaml fence if any. When that is not a YAML list by itself, stray prose before the
    first `- type:` line and after the list is cut away.
    """
    return extract_with_list(text)[0].strip()


def extract_with_list(text: str) -> tuple[str, Any]:
    """`extract_yaml`'s text and, when it already parsed as a YAML list there, the list (else None). Without the
    list, the text comes after blank lines in place of the prose cut before it, so that a YAML error's line is the
    line of the YAML body (a scene file's own, after a comment: before, it was counted from the first item)."""
    body = _strip_wrappers(text)
    try:
        data = load_yaml(body)
        if isinstance(data, list):
            return body.strip(), data
    except SceneError:
        pass
    start, part = _cut_prose(body) or (0, body)
    lead = len(part) - len(part.lstrip())
    return "\n" * _line_breaks(body[:start] + part[:lead]) + part.strip(), None
