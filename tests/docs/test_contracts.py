"""docs/CONTRACTS.md states signatures that the code has: each is checked with
``inspect.signature`` (``dataclasses.fields`` for a dataclass), so the doc cannot drift.

The doc's rules (stated at its top):

* A code span shaped like a call, ``name(params)`` or ``name(params) -> ret``, is a
  signature and is checked; there is no other marker and no way to skip one. A span
  of that shape that does not parse or does not resolve fails, naming its line.
* ``name`` resolves in the module named by the nearest heading above that carries one
  in a code span (``## storage (`bigT.storage`)``): as an attribute of that module, as
  a submodule path below it (``runner.open_runner``), or as an absolute dotted path
  (``bigT.scenes.load``). ``BlockCSR.get_tile_row(i)`` is a method: ``self`` is not
  written.
* Parameter names, their order, their kinds (positional, keyword-only after ``*``,
  ``*args``, ``**kwargs``) and their defaults must be the code's. A default is written
  as the code writes it and evaluated in the defining module (``config.DEFAULT_BATCH``
  works). A dataclass lists its fields in order; defaults, where written, are checked.
* ``-> Name`` is checked against the return annotation when the doc writes a plain
  name and the code annotates one; any other text after ``->`` is prose.

``BIGT_DOCS=/some/dir`` checks ``/some/dir/CONTRACTS.md`` instead of docs/ (to show
what the test finds in an old copy).
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOC = Path(os.environ.get("BIGT_DOCS", ROOT / "docs")) / "CONTRACTS.md"

_FENCE = re.compile(r"^```.*?^```[^\n]*$", re.DOTALL | re.MULTILINE)
_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")
#: A call-shaped span: a name (dotted, maybe with a leading dot or <placeholder>) and "(".
_CALL = re.compile(r"^\.?[A-Za-z_<][\w.<>]*\(")
_MODULE = re.compile(r"^bigT(\.\w+)*$")
_EMPTY = inspect.Parameter.empty


@dataclass(frozen=True)
class DocSignature:
    """One call-shaped code span of the doc."""

    line: int
    text: str
    module: str | None  # of the section it is in

    @property
    def where(self) -> str:
        return f"{DOC.name}:{self.line}"


def _without_fences(text: str) -> str:
    """The doc with fenced blocks blanked (their line count kept)."""
    return _FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def doc_signatures(path: Path = DOC) -> list[DocSignature]:
    """Every call-shaped code span of the doc, with its line and its section's module."""
    text = _without_fences(path.read_text(encoding="utf-8"))
    lines = text.splitlines()
    found = []
    # spans may run over a line break (inside a paragraph): find them in the whole text
    module_at = _section_modules(text)
    for m in _SPAN.finditer(text):
        span = " ".join(m.group(1).split())
        line = text.count("\n", 0, m.start()) + 1
        if lines[line - 1].lstrip().startswith("#"):
            continue  # a heading's module name
        if _CALL.match(span):
            found.append(DocSignature(line, span, module_at(line)))
    return found


def _section_modules(text: str):
    """A function: line number -> the module of the innermost heading above naming one."""
    marks = []  # (line, stack of (level, module))
    stack: list[tuple[int, str | None]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        heading = re.match(r"^(#+)\s", line)
        if not heading:
            continue
        level = len(heading.group(1))
        stack = [(lv, mod) for lv, mod in stack if lv < level]
        named = [s.strip() for s in _SPAN.findall(line) if _MODULE.match(s.strip())]
        stack.append((level, named[-1] if named else None))
        marks.append((number, [mod for _, mod in stack if mod]))

    def module_at(line: int) -> str | None:
        current = None
        for number, mods in marks:
            if number > line:
                break
            current = mods[-1] if mods else None
        return current

    return module_at


# --- the doc's side -------------------------------------------------------------------

@dataclass(frozen=True)
class Param:
    name: str
    kind: inspect._ParameterKind
    default: object = _EMPTY


class DocError(Exception):
    """A span that is not a signature the test can read or resolve."""


def split_signature(text: str) -> tuple[str, str, str | None]:
    """(name, parameter text, return text or None) of ``name(params) -> ret``."""
    start = text.index("(")
    depth = 0
    for i in range(start, len(text)):
        depth += {"(": 1, ")": -1}.get(text[i], 0)
        if depth == 0:
            break
    else:
        raise DocError("unbalanced parentheses")
    rest = text[i + 1:].strip()
    if rest and not rest.startswith("->"):
        raise DocError(f"text after the parameters that is not '-> ...': {rest!r}")
    return text[:start], text[start + 1:i], rest[2:].strip() or None if rest else None


def doc_params(params: str, namespace: dict) -> list[Param]:
    """The parameters written in the doc, defaults evaluated in ``namespace``."""
    try:
        tree = ast.parse(f"def _f({params}): pass")
    except SyntaxError as exc:
        raise DocError(f"parameters are not Python ({exc.msg})") from None
    a = tree.body[0].args
    positional = [(p, inspect.Parameter.POSITIONAL_ONLY) for p in a.posonlyargs]
    positional += [(p, inspect.Parameter.POSITIONAL_OR_KEYWORD) for p in a.args]
    defaults = [None] * (len(positional) - len(a.defaults)) + list(a.defaults)
    out = [Param(p.arg, kind, _value(d, namespace)) for (p, kind), d in zip(positional, defaults)]
    if a.vararg:
        out.append(Param(a.vararg.arg, inspect.Parameter.VAR_POSITIONAL))
    out += [Param(p.arg, inspect.Parameter.KEYWORD_ONLY, _value(d, namespace))
            for p, d in zip(a.kwonlyargs, a.kw_defaults)]
    if a.kwarg:
        out.append(Param(a.kwarg.arg, inspect.Parameter.VAR_KEYWORD))
    return out


def _value(node, namespace: dict):
    if node is None:
        return _EMPTY
    source = ast.unparse(node)
    try:
        return eval(source, dict(namespace))  # our own doc's defaults
    except Exception as exc:  # noqa: BLE001 - any failure is the doc's, reported
        raise DocError(f"default {source!r} does not evaluate in the defining module "
                       f"({type(exc).__name__}: {exc})") from None


# --- the code's side ------------------------------------------------------------------

def resolve(name: str, module: str | None):
    """(object, the class it is a method of or None) for the doc's ``name``."""
    if not re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", name):
        raise DocError(f"{name!r} is not a (dotted) Python name")
    tries = ([f"{module}.{name}"] if module else []) + [name]
    for dotted in tries:
        parts = dotted.split(".")
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            owner = None
            try:
                for attr in parts[cut:]:
                    owner, obj = obj, getattr(obj, attr)
            except AttributeError:
                break
            return obj, owner if inspect.isclass(owner) else None
    where = f" in {module}" if module else ""
    raise DocError(f"{name!r} does not resolve{where} (nor as an absolute path)")


def code_params(obj, owner) -> list[Param]:
    """The code's parameters; a method's ``self`` left out."""
    if dataclasses.is_dataclass(obj) and inspect.isclass(obj):
        return [Param(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD, _field_default(f))
                for f in dataclasses.fields(obj)]
    params = list(inspect.signature(obj).parameters.values())
    unbound = owner is not None and inspect.isfunction(
        inspect.getattr_static(owner, obj.__name__, None))
    if unbound and params:
        params = params[1:]
    return [Param(p.name, p.kind, p.default) for p in params]


def _field_default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return _EMPTY


def _namespace(obj) -> dict:
    """Globals of the module that defines ``obj`` (where its defaults are written)."""
    module = sys.modules.get(getattr(obj, "__module__", None) or "")
    return dict(vars(module)) if module else {}


def _same(a, b) -> bool:
    if a is _EMPTY or b is _EMPTY:
        return a is b
    try:
        return a is b or (type(a) is type(b) and bool(a == b))
    except Exception:  # noqa: BLE001 - values that do not compare (arrays) differ
        return False


def render(params: list[Param]) -> str:
    """``a, b=1, *, c=None`` (defaults by repr, as the doc writes them)."""
    out, star = [], False
    for p in params:
        if p.kind == inspect.Parameter.KEYWORD_ONLY and not star:
            out.append("*")
            star = True
        if p.kind == inspect.Parameter.VAR_POSITIONAL:
            out.append(f"*{p.name}")
            star = True
        elif p.kind == inspect.Parameter.VAR_KEYWORD:
            out.append(f"**{p.name}")
        else:
            out.append(p.name if p.default is _EMPTY else f"{p.name}={p.default!r}")
    if any(p.kind == inspect.Parameter.POSITIONAL_ONLY for p in params):
        last = max(i for i, p in enumerate(params) if p.kind == inspect.Parameter.POSITIONAL_ONLY)
        out.insert(last + 1, "/")
    return ", ".join(out)


def mismatches(doc: list[Param], code: list[Param], dataclass_fields: bool) -> list[str]:
    """What differs, in words (empty when the doc is right): names missing or gone, the
    order, then the kind and default of every parameter both name."""
    problems = []
    doc_names, code_names = [p.name for p in doc], [p.name for p in code]
    missing = [n for n in code_names if n not in doc_names]
    extra = [n for n in doc_names if n not in code_names]
    if missing:
        problems.append(f"missing {', '.join(missing)}")
    if extra:
        problems.append(f"no longer in the code: {', '.join(extra)}")
    common = [n for n in doc_names if n in code_names]
    if common != [n for n in code_names if n in doc_names]:
        problems.append("order differs")
    actual = {p.name: p for p in code}
    for d in doc:
        c = actual.get(d.name)
        if c is None:
            continue
        if d.kind != c.kind and not dataclass_fields:
            problems.append(f"{d.name} is {c.kind.description} in the code, "
                            f"{d.kind.description} in the doc")
        if dataclass_fields and d.default is _EMPTY:
            continue  # a dataclass's fields may be listed without their defaults
        if not _same(d.default, c.default):
            problems.append(f"default of {d.name}: code {_shown(c.default)}, "
                            f"doc {_shown(d.default)}")
    return problems


def _shown(default) -> str:
    return "none (required)" if default is _EMPTY else repr(default)


def _return_text(obj) -> str | None:
    """The code's return annotation as text (None for a class or none given)."""
    if inspect.isclass(obj):
        return None
    annotation = inspect.signature(obj).return_annotation
    if annotation is _EMPTY:
        return None
    return (annotation if isinstance(annotation, str)
            else getattr(annotation, "__name__", str(annotation))).strip("'\"")


def _annotation(obj) -> str:
    text = _return_text(obj)
    return f" -> {text}" if text else ""


def _return_problem(obj, ret: str | None) -> str | None:
    text = _return_text(obj)
    if ret is None or text is None or not re.fullmatch(r"[A-Za-z_][\w.]*", ret):
        return None
    simple = re.fullmatch(r"[A-Za-z_][\w.]*", text)
    ours = text.rsplit(".", 1)[-1] if simple else text
    if ours != ret.rsplit(".", 1)[-1]:
        return f"returns {text} in the code, {ret} in the doc"
    return None


def check(sig: DocSignature) -> list[str]:
    """The problems of one documented signature, each a full message."""
    head = f"{sig.where}: documented `{sig.text}`"
    try:
        name, params, ret = split_signature(sig.text)
        if name.startswith("."):
            raise DocError(f"{name!r} starts with '.': write the class, Class{name}")
        obj, owner = resolve(name, sig.module)
        is_fields = dataclasses.is_dataclass(obj) and inspect.isclass(obj)
        code = code_params(obj, owner)
        doc = doc_params(params, _namespace(obj))
    except DocError as exc:
        return [f"{head}: {exc}"]
    problems = mismatches(doc, code, is_fields)
    problem = _return_problem(obj, ret)
    if problem:
        problems.append(problem)
    if not problems:
        return []
    kind = "dataclass fields" if is_fields else "actual"
    actual = f"{name}({render(code)}){_annotation(obj)}"
    return [f"{head}; {kind}: {actual}: {'; '.join(problems)}"]


SIGNATURES = doc_signatures()


@pytest.mark.parametrize("sig", SIGNATURES, ids=[f"{s.line}-{s.text.split('(')[0]}"
                                               for s in SIGNATURES])
def test_documented_signature_is_the_codes(sig):
    problems = check(sig)
    if problems:
        pytest.fail("\n".join(problems), pytrace=False)


def test_the_doc_states_signatures_under_modules():
    """The parser finds the doc's signatures (a doc rewritten into another shape would
    otherwise pass with nothing checked), each section's module imports, and every
    signature is in a section that names one."""
    assert len(SIGNATURES) >= 40, f"only {len(SIGNATURES)} signatures found in {DOC}"
    text = _without_fences(DOC.read_text(encoding="utf-8"))
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("#"):
            for span in _SPAN.findall(line):
                if _MODULE.match(span.strip()):
                    importlib.import_module(span.strip())
    orphans = [s.where for s in SIGNATURES if s.module is None]
    assert not orphans, f"signatures outside a section naming its module: {orphans}"
