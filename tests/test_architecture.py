"""The house rules, read from the code: no import loop in addon/, bpy only where Blender is the point, one writer
per step folder.

Every import counts, module-level or inside a function: an import hidden in a
function still ties two modules together, and a loop through it is still a loop.
"""

from __future__ import annotations

import ast
import functools
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ADDON = ROOT / "addon"
#: Where importing bpy is the point; addon/native.py loads bpy before pymeshlab (shared Embree, see its doc).
BPY_ALLOWED = ("addon/blender/", "addon/lab/", "operators/", "panels/", "blender_registration.py", "addon/native.py")


def _module(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(["procam", *parts])


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The syntax tree of ``path``, parsed once for every rule that reads it (read-only)."""
    return ast.parse(path.read_text(), str(path))


@functools.cache
def _imports(path: Path) -> frozenset[str]:
    """The modules ``path`` imports (absolute names, relative imports resolved; ``from x import y`` gives x.y when
    y is a module of ours, else x)."""
    tree = _tree(path)
    here = _module(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[:len(package) - node.level + 1] if node.level else []
            name = ".".join([*base, *(node.module.split(".") if node.module else [])])
            for alias in node.names:
                out.add(f"{name}.{alias.name}")
            out.add(name)
    return frozenset(out)


def _graph() -> dict[str, set[str]]:
    files = {_module(p): p for p in ADDON.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        graph[name] = {m for m in _imports(path) if m in files and m != name and not name.startswith(m + ".")}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_between_files():
    assert _cycles(_graph()) == []


def test_no_import_cycle_between_folders():
    folders: dict[str, set[str]] = defaultdict(set)

    def folder(m: str) -> str:
        parts = m.split(".")
        return ".".join(parts[:3]) if len(parts) > 3 else m  # procam.addon.<folder or module>

    for a, targets in _graph().items():
        for b in targets:
            if folder(a) != folder(b):
                folders[folder(a)].add(folder(b))
    assert _cycles(dict(folders)) == []


def test_bpy_only_where_blender_is_the_point():
    offenders = []
    for path in [*ROOT.glob("*.py"), *ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"),
                 *(ROOT / "panels").rglob("*.py")]:
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(BPY_ALLOWED):
            continue
        if {m for m in _imports(path) if m == "bpy" or m.startswith(("bpy.", "mathutils"))}:
            offenders.append(rel)
    assert offenders == []


#: Why an import of our own may wait inside a function: it loads bpy (Blender's bridge and the Cycles lab), or cv2
#: where Blender registers the extension (type-checking imports sit at module level). Anything else goes at the top
#: of the file, where a reader sees what the module depends on.
LAZY_ALLOWED = ("blender", "cycles", "imageio", "cli.app", "addon.jobs")


def test_own_imports_at_module_level():
    offenders = []
    for path in [*ROOT.glob("*.py"), *ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"),
                 *(ROOT / "panels").rglob("*.py")]:
        tree = _tree(path)
        for func in ast.walk(tree):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if isinstance(node, ast.ImportFrom) and node.level:
                    names = [".".join(filter(None, (node.module, a.name))) for a in node.names]
                    if not all(any(word in name for word in LAZY_ALLOWED) for name in names):
                        offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} {ast.unparse(node)}")
    assert offenders == []


def test_step_folders_are_written_by_steps_only():
    """Manifests of step folders are named in steps/layout.py alone; nothing outside steps/ spells them."""
    names = ("calibration.json", "compensation.json", "show.json", "metrics.json", "gap.json", "frames.json")
    offenders = [f"{p.relative_to(ROOT)}: {n}" for p in [*ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"),
                                                          *(ROOT / "panels").rglob("*.py")]
                 if "steps" not in p.relative_to(ADDON if p.is_relative_to(ADDON) else ROOT).parts
                 for n in names if f'"{n}"' in p.read_text()]
    assert offenders == []


def test_the_graph_reader_sees_a_loop():
    """The cycle finder is not vacuous: a two-module loop is found."""
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]


#: Keys under which ProCam manifests name files and folders (a frame, a mesh, a pattern …).
FILE_KEYS = {"file", "files", "frame", "input", "simulated", "target", "mesh", "pattern", "image", "capture",
             "uncompensated", "classical", "path", "folder", "name", "source"}
#: Calls whose first argument is a file ProCam writes into its own output (a name it chose), not one it reads.
WRITERS = {"write_image", "write_atomic_bytes", "write_manifest"}
def _manifest_value(node: ast.AST) -> bool:
    """``d["file"]``, ``d.get("file")`` or ``str()`` of one: a value read from a manifest under a file key."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "str" and node.args:
        return _manifest_value(node.args[0])
    if isinstance(node, ast.Subscript):
        key = node.slice
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" and node.args:
        key = node.args[0]
    else:
        return False
    return isinstance(key, ast.Constant) and key.value in FILE_KEYS


def _path_joins_of_manifest_values(tree: ast.AST) -> list[ast.AST]:
    written = {id(call.args[0]) for call in ast.walk(tree) if isinstance(call, ast.Call) and call.args
               and (call.func.id if isinstance(call.func, ast.Name) else getattr(call.func, "attr", "")) in WRITERS}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div) and _manifest_value(node.right):
            if id(node) not in written:
                found.append(node)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("joinpath", "with_name", "join") and any(map(_manifest_value, node.args)):
            found.append(node)
    return found


def test_paths_read_from_manifests_go_through_safepaths():
    """No reader joins a file name taken from a manifest onto a folder itself: ``safepaths.inside`` resolves it, so
    an absolute name, ``..`` or a link leaving the folder is refused in one place."""
    files = [*ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"), *(ROOT / "panels").rglob("*.py")]
    offenders = [f"{p.relative_to(ROOT)}: {ast.unparse(node)}" for p in sorted(files)
                 for node in _path_joins_of_manifest_values(_tree(p))]
    assert offenders == []


def test_the_manifest_path_scan_sees_a_join():
    """The scan is not vacuous: the joins the readers used to make are found, writes into our own output are not."""
    code = """
def read(folder, doc, t, e):
    a = folder / t["frame"]
    b = root / str(e.get("file", ""))
    c = path.with_name(doc["surface"]["mesh"])
    write_image(folder.tmp / files["input"], x)
    d = sig / e["gain"]
"""
    found = [ast.unparse(n) for n in _path_joins_of_manifest_values(ast.parse(code))]
    assert found == ["folder / t['frame']", "root / str(e.get('file', ''))", "path.with_name(doc['surface']['mesh'])"]


def test_steps_never_import_the_blender_side():
    """The steps run where Blender is not: what writes a .blend is handed to them (``blend_writer``), never
    imported, not even inside a function."""
    for path in sorted((ADDON / "steps").glob("*.py")):
        blender = sorted(m for m in _imports(path) if m in ("procam.addon.blender", "bpy") or
                         m.startswith(("procam.addon.blender.", "bpy.")))
        assert not blender, f"{path.relative_to(ROOT)} imports {blender}"


def test_only_the_lab_knows_the_rig_of_other_forms():
    """The lab of other forms (addon/lab/other_forms.py) is what the models are not: no model, stage or diagnosis may
    import it, or it would stop being independent of them; evaluation code (tests, benchmarks) may."""
    users = sorted(str(p.relative_to(ROOT)) for p in ROOT.rglob("*.py")
                   if ".venv" not in p.parts and "procam.addon.lab.other_forms" in _imports(p))
    assert users and all(u.startswith(("addon/lab/", "tests/", "scripts/bench_")) for u in users), users


#: Handlers of every exception that neither re-raise nor let a cancel pass first, and why no cancel reaches them:
#: file and function.
CATCH_ALL_ALLOWED = {
    ("addon/cli/app.py", "main"),  # its first one guards building the parser; the command's own lets Cancelled pass
    ("addon/jobs.py", "pump"),  # hands the exception to the worker, which raises it
    ("addon/blender/rig.py", "rig_summary"),  # the panel's text about the scene's rig objects
    ("addon/lab/cycles_device.py", "__del__"),  # closing a forgotten lab at interpreter shutdown
    ("addon/outputs.py", "_pid_alive"),  # asking Windows whether a process still runs
}


def _sources() -> list[Path]:
    return [*ROOT.glob("*.py"), *ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"),
            *(ROOT / "panels").rglob("*.py")]


def _names(handler: ast.ExceptHandler) -> set[str]:
    kinds = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return {ast.unparse(k).rsplit(".", 1)[-1] for k in kinds if k is not None}


def test_a_cancel_is_not_an_error_the_user_can_fix():
    """``Cancelled`` is not a ProCamError: the handlers that record a failed target and go on, or turn one error
    into another, catch ProCamError, and a cancel must pass them all (a cancelled evaluation once committed a
    folder with a failed row, then reported it unchanged). So no handler re-raises it first any more; and one that
    catches every exception lets it pass first, re-raises, or is known to be out of a cancel's reach."""
    from procam.addon.errors import Cancelled, ProCamError

    assert not issubclass(Cancelled, ProCamError) and Cancelled.exit_code == 130
    reraise_first, catch_all = [], []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        tree = _tree(path)
        funcs = [f for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))]
        for node in ast.walk(tree):
            if not isinstance(node, ast.Try):
                continue
            around = [f for f in funcs if f.lineno <= node.lineno <= f.end_lineno]
            where = max(around, key=lambda f: f.lineno).name if around else ""
            passed = False
            for handler in node.handlers:
                names = _names(handler) if handler.type is not None else {"BaseException"}
                bare_raise = len(handler.body) == 1 and isinstance(handler.body[0], ast.Raise) \
                    and handler.body[0].exc is None
                if names == {"Cancelled"} and bare_raise:
                    reraise_first.append(f"{rel}:{handler.lineno}")
                passed |= "Cancelled" in names
                last = handler.body[-1]
                reraises = isinstance(last, ast.Raise) and last.exc is None  # not turned into another error
                if names & {"Exception", "BaseException"} and not passed and not reraises \
                        and (rel, where) not in CATCH_ALL_ALLOWED:
                    catch_all.append(f"{rel}:{handler.lineno} in {where}")
    assert reraise_first == [] and catch_all == []


def _sources() -> list[Path]:
    return [*ADDON.rglob("*.py"), *(ROOT / "operators").rglob("*.py"), *(ROOT / "panels").rglob("*.py")]


def test_one_definition_of_each_shared_helper():
    """What several modules need is written once: one reader of mesh files, one list of the image files a folder
    of images is listed with (the capture-set format's own list of what a set stores is a format rule, not a
    reader's), one sRGB transfer (its break points spelled in colour.py alone)."""
    srgb = sorted(p.relative_to(ROOT).as_posix() for p in _sources()
                  if "0.0031308" in p.read_text() or "0.04045" in p.read_text())
    assert srgb == ["addon/colour.py"]
    mesh_readers = sorted(p.relative_to(ROOT).as_posix() for p in _sources() if "load_new_mesh(" in p.read_text())
    assert mesh_readers == ["addon/surface/mesh.py"]
    image_lists = []
    for path in _sources():
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Tuple) and {".jpg", ".png"} <= {getattr(e, "value", None) for e in node.elts}:
                image_lists.append(path.relative_to(ROOT).as_posix())
    assert image_lists == ["addon/imageio.py"]
