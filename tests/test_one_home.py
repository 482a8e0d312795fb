"""Each limit and each word of the job vocabulary has one home in the product (service/,
worker/, model/ and the page): these tests read the source and fail when one is spelled again
somewhere else, so that changing it in its home changes it everywhere. Documents and tests
may repeat them; docstrings and comments may name them.

The homes: job states and kinds in ``service/vocabulary.py``; the tileable sampler's file
name, the planes and the tile, volume and bake bounds in ``worker/contract.py``; the fit
budget and its cap in ``service/settings.py``. The page and the Python client read the
limits in force from ``GET /v1/limits``.
"""
from __future__ import annotations

import ast
import re
from collections import Counter
from pathlib import Path

from service.settings import FIT_SECONDS, MAX_FIT_SECONDS
from service.vocabulary import JobKind, JobState
from worker import contract

ROOT = Path(__file__).resolve().parents[1]
VOCABULARY = "service/vocabulary.py"
CONTRACT = "worker/contract.py"
SETTINGS = "service/settings.py"

#: the same words or numbers meaning something else: (file, value) -> (how many, what)
OTHER_MEANINGS = {
    ("service/errors.py", "canceled"): (1, "the problem type urn:texspace:problem:canceled"),
    ("service/schemas.py", "queued"): (2, "a refinement's stage: waiting for its first turn"),
    ("service/cli.py", 1024): (1, "the most worker threads --workers takes"),
}


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def python_files() -> list[Path]:
    """The product's Python, less the migrations (frozen in time: they keep the values they
    wrote, whatever the code calls them later)."""
    return [path for package in ("service", "worker", "model") for path in sorted((ROOT / package).rglob("*.py"))
            if "__pycache__" not in path.parts and "alembic" not in path.parts]


def page_files() -> list[Path]:
    static = ROOT / "service" / "static"
    return [path for path in sorted(static.rglob("*")) if path.suffix in (".js", ".html") and "vendor" not in path.parts]


class Spellings(ast.NodeVisitor):
    """The code constants of one module and what holds each: ``"bound"`` (``le=`` / ``lt=``, a
    comparison, an argument of ``ranged``, a ``Field``'s default), ``"lower"`` (``ge=`` /
    ``gt=``), ``"key"`` (a dict key or a subscript: it names a field, it states no value),
    ``"prose"`` (an f-string's text) or ``"value"``; and each tuple, list, set or dict keyed by
    strings only, as the frozenset of those strings (``"collection"``). Docstrings and other
    bare strings are prose, left out."""

    def __init__(self) -> None:
        self.found: list[tuple[object, int, str]] = []
        self.role: dict[int, str] = {}

    def visit_Expr(self, node: ast.Expr) -> None:
        if not (isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)):
            self.generic_visit(node)

    def visit_Dict(self, node: ast.Dict) -> None:
        for key in node.keys:
            if key is not None:
                self.role[id(key)] = "key"
        words = [k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)]
        if words and len(words) == len(node.keys):  # a table keyed by them lists them too
            self.found.append((frozenset(words), node.lineno, "collection"))
        self.generic_visit(node)

    def visit_Subscript(self, node: ast.Subscript) -> None:
        self.role[id(node.slice)] = "key"
        self.generic_visit(node)

    def visit_keyword(self, node: ast.keyword) -> None:
        if node.arg in ("le", "lt", "ge", "gt"):
            self.role[id(node.value)] = "bound" if node.arg in ("le", "lt") else "lower"
        self.generic_visit(node)

    def visit_Compare(self, node: ast.Compare) -> None:
        for operand in (node.left, *node.comparators):
            self.role.setdefault(id(operand), "bound")
            for item in getattr(operand, "elts", ()):  # x in (a, b)
                self.role.setdefault(id(item), "bound")
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        if getattr(node.func, "id", None) == "ranged":
            for arg in node.args:
                self.role[id(arg)] = "bound"
        if getattr(node.func, "id", None) == "Field" and node.args:
            self.role[id(node.args[0])] = "bound"
        self.generic_visit(node)

    def visit_JoinedStr(self, node: ast.JoinedStr) -> None:
        for part in node.values:
            self.role[id(part)] = "prose"
        self.generic_visit(node)

    def visit_Constant(self, node: ast.Constant) -> None:
        self.found.append((node.value, node.lineno, self.role.get(id(node), "value")))

    def visit_Tuple(self, node: ast.Tuple | ast.List | ast.Set) -> None:
        words = [e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)]
        if words and len(words) == len(node.elts):
            self.found.append((frozenset(words), node.lineno, "collection"))
        self.generic_visit(node)

    visit_List = visit_Set = visit_Tuple


def spellings(path: Path) -> list[tuple[object, int, str]]:
    """(constant, line, role) of every constant in ``path`` that is code (``Spellings``)."""
    visitor = Spellings()
    visitor.visit(ast.parse(path.read_text(), str(path)))
    return visitor.found


def test_the_finder_tells_code_from_prose(tmp_path: Path) -> None:
    source = tmp_path / "m.py"
    source.write_text('"""queued in a docstring"""\nx = {"failed": 0}\nif s == "running" and n <= 1024:\n'
                      '    y = Field(1024, ge=1024, le=8192, description=f"{n} canceled")\nplanes = ("xy", "xz", "yz")\n')
    found = {(value, role) for value, _, role in spellings(source)}
    assert ("queued", "value") not in found and ("failed", "key") in found and (" canceled", "prose") in found
    assert Counter(role for value, _, role in spellings(source) if value == 1024) == {"bound": 2, "lower": 1}
    assert {("running", "bound"), (1024, "bound"), (8192, "bound"), (frozenset(contract.PLANES), "collection")} <= found


def test_job_states_are_spelled_only_in_the_vocabulary() -> None:
    states = {state.value for state in JobState}
    seen: Counter[tuple[str, str]] = Counter()
    lines: dict[tuple[str, str], list[int]] = {}
    for path in python_files():
        if rel(path) == VOCABULARY:
            continue
        for value, line, role in spellings(path):
            if isinstance(value, str) and value in states and role not in ("key", "prose"):
                seen[(rel(path), value)] += 1
                lines.setdefault((rel(path), value), []).append(line)
    spelled = [f"{where}:{lines[(where, value)]} spells the job state {value!r}: use JobState"
               for (where, value), count in sorted(seen.items())
               if count != OTHER_MEANINGS.get((where, value), (0, ""))[0]]
    assert not spelled, "\n".join(spelled)


def test_job_kinds_are_compared_and_passed_only_through_the_vocabulary() -> None:
    """A kind is named by JobKind wherever code compares or passes one (``kind == ...``,
    ``kind=...``, a kinds table); the same words elsewhere are lanes, folders, texture
    sources or CLI commands."""
    kinds = {kind.value for kind in JobKind}
    spelled = []
    for path in python_files():
        if rel(path) == VOCABULARY:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            words = []
            if isinstance(node, ast.Compare) and any(_names_kind(side) for side in (node.left, *node.comparators)):
                words = [c.value for side in (node.left, *node.comparators)
                         for c in (getattr(side, "elts", None) or [side]) if isinstance(c, ast.Constant)]
            elif isinstance(node, ast.keyword) and node.arg == "kind" and isinstance(node.value, ast.Constant):
                words = [node.value.value]
            elif isinstance(node, ast.Dict) and kinds <= {getattr(k, "value", None) for k in node.keys}:
                words = [k.value for k in node.keys]
            spelled += [f"{rel(path)}:{node.lineno} spells the job kind {word!r}: use JobKind"
                        for word in words if word in kinds]
    assert not spelled, "\n".join(spelled)


def _names_kind(node: ast.expr) -> bool:
    return getattr(node, "attr", None) == "kind" or getattr(node, "id", None) == "kind"


def test_limits_are_spelled_only_in_their_homes() -> None:
    """The tileable sampler's file name, the bake bound (8192), the tile and volume bound
    (1024, as a bound), the fit cap (3600 s, as a bound) and the planes, outside their homes."""
    spelled = []
    for path in python_files():
        where, by_1024 = rel(path), []
        for value, line, role in spellings(path):
            at = f"{where}:{line}"
            if where != CONTRACT:
                if isinstance(value, str) and contract.TILEABLE_SAMPLER in value:
                    spelled.append(f"{at} spells {contract.TILEABLE_SAMPLER!r}: use worker.contract.TILEABLE_SAMPLER")
                if type(value) is int and value == contract.MAX_BAKE_RESOLUTION:
                    spelled.append(f"{at} spells {value}: use worker.contract.MAX_BAKE_RESOLUTION")
                if type(value) is int and value == contract.MAX_TILE_SIZE and role == "bound":
                    by_1024.append(line)
                if role == "collection" and value == frozenset(contract.PLANES):
                    spelled.append(f"{at} lists the planes: use worker.contract.PLANES")
            if where != SETTINGS and value == MAX_FIT_SECONDS and role == "bound":
                spelled.append(f"{at} bounds by {value:g}: use service.settings.MAX_FIT_SECONDS")
        if len(by_1024) != OTHER_MEANINGS.get((where, contract.MAX_TILE_SIZE), (0, ""))[0]:
            spelled.append(f"{where}:{by_1024} bounds by {contract.MAX_TILE_SIZE}: use worker.contract's "
                           "MAX_TILE_SIZE or MAX_VOLUME_RESOLUTION, or the setting")
    assert not spelled, "\n".join(spelled)


def test_the_formats_each_output_offers_are_listed_only_in_the_registry() -> None:
    """A tuple or list of two or more formats one output offers (worker.files.OFFERED) is a
    copy of the registry anywhere but worker/files.py; the page reads them from /v1/limits."""
    from worker.files import OFFERED

    lists = {frozenset(names) for names in OFFERED.values()}
    # the volume writers' table, one class per format, held equal to the registry by tests/worker/test_files.py
    writers = ("worker/volume_writers.py", frozenset(OFFERED["volume"]))
    spelled = [f"{rel(path)}:{line} lists the formats {sorted(value)}: use worker.files.OFFERED"
               for path in python_files() if rel(path) != "worker/files.py"
               for value, line, role in spellings(path)
               if role == "collection" and value in lists and (rel(path), value) != writers]
    quoted = re.compile(r"""\[\s*['"](?:npy|glb|png)['"]\s*,""")  # a JavaScript list of formats
    spelled += [f"{rel(path)} lists formats" for path in page_files() if quoted.search(path.read_text())]
    assert not spelled, "\n".join(spelled)


def test_the_page_reads_its_limits_from_the_api() -> None:
    """The page (service/static) spells no bound, file name or plane list: GET /v1/limits
    answers them (main.js applyLimits)."""
    copied = {
        str(contract.MAX_BAKE_RESOLUTION): re.compile(rf"\b{contract.MAX_BAKE_RESOLUTION}\b"),
        contract.TILEABLE_SAMPLER: re.compile(re.escape(contract.TILEABLE_SAMPLER)),
        "a quoted plane": re.compile(r"""['"](?:xz|yz)['"]"""),
        "the fit budget": re.compile(r"""id="fit-seconds"[^>]*\b(?:value|max)="""),
    }
    spelled = [f"{rel(path)}:{text.count(chr(10), 0, match.start()) + 1} spells {what}"
               for path in page_files() for text in [path.read_text()]
               for what, pattern in copied.items() for match in pattern.finditer(text)]
    assert not spelled, "\n".join(spelled)


def test_the_fit_scripts_default_is_the_services_budget() -> None:
    """``python -m model.fit`` keeps a default of its own (model/ may not import the service):
    it is the service's budget, read from the source so that torch need not be imported."""
    tree = ast.parse((ROOT / "model" / "fit.py").read_text())
    seconds = next(node.value.value for node in tree.body if isinstance(node, ast.Assign)
                   and any(getattr(t, "id", None) == "DEFAULT_SECONDS" for t in node.targets))
    assert seconds == FIT_SECONDS
