"""Files and data read by the project's code: YAML through safe_load only (no object construction),
no eval/exec/pickle-like loading of anything, no file path taken from message content.

An AST scan of every Python file under ros_ws/src (both cells): it cannot be fooled by comments
or strings, and a new file is covered without changing this test."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[2]
SOURCES = sorted(p for p in (ROOT / "ros_ws" / "src").rglob("*.py") if "build" not in p.parts)

UNSAFE_CALLS = {
    ("yaml", "load"), ("yaml", "unsafe_load"), ("yaml", "full_load"), ("yaml", "load_all"),
    ("yaml", "unsafe_load_all"), ("yaml", "full_load_all"),
    ("pickle", "load"), ("pickle", "loads"), ("pickle", "Unpickler"), ("marshal", "load"), ("marshal", "loads"),
    ("shelve", "open"), ("dill", "load"), ("dill", "loads"), ("joblib", "load"), ("torch", "load"),
}
UNSAFE_NAMES = {"eval", "exec", "compile", "__import__"}
UNSAFE_MODULES = {"pickle", "cPickle", "marshal", "shelve", "dill", "joblib"}
PATH_SINKS = {"open", "Path", "PurePath", "join", "mkdir", "write_text", "write_bytes", "rmtree", "remove", "unlink",
              "replace", "rename", "write_yaml", "write_json_atomic", "Rosbag2McapWriter"}
MSG_ARGS = {"msg", "request", "data"}


def _call_name(node):
    f = node.func
    if isinstance(f, ast.Attribute):
        base = f.value.id if isinstance(f.value, ast.Name) else (f.value.attr if isinstance(f.value, ast.Attribute) else "")
        return base, f.attr
    if isinstance(f, ast.Name):
        return "", f.id
    return "", ""


def _uses(node, names):
    return any(isinstance(n, ast.Name) and n.id in names for n in ast.walk(node))


def test_sources_found():
    assert len(SOURCES) > 30 and any(p.name == "mcap_io.py" for p in SOURCES)


def test_no_unsafe_loading():
    problems = []
    for path in SOURCES:
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', '?')}"
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                mods = [a.name.split(".")[0] for a in node.names] if isinstance(node, ast.Import) else \
                    [(node.module or "").split(".")[0]]
                bad = set(mods) & UNSAFE_MODULES
                if bad:
                    problems.append(f"{where}: imports {bad}")
            if isinstance(node, ast.Call):
                base, name = _call_name(node)
                if (base, name) in UNSAFE_CALLS or (not base and name in UNSAFE_NAMES):
                    problems.append(f"{where}: calls {base + '.' if base else ''}{name}")
                if name == "load" and base in ("np", "numpy"):
                    for kw in node.keywords:
                        if kw.arg == "allow_pickle" and not (isinstance(kw.value, ast.Constant) and kw.value.value is False):
                            problems.append(f"{where}: np.load with allow_pickle")
                if base == "yaml" and name not in ("safe_load", "safe_dump", "safe_load_all", "dump", "YAMLError"):
                    problems.append(f"{where}: yaml.{name}")
                if name in ("Loader", "UnsafeLoader", "FullLoader"):
                    problems.append(f"{where}: yaml loader {name}")
    assert not problems, "\n".join(problems)


def test_no_path_from_message_content():
    """In the node layer, no callback argument (a message or a service request) reaches a call that
    opens, creates, moves or deletes files."""
    problems = []
    for path in SOURCES:
        if "nodes" not in path.parent.name and path.name != "offline.py":
            continue
        tree = ast.parse(path.read_text(), str(path))
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.Lambda)):
                continue
            args = {a.arg for a in fn.args.args} & MSG_ARGS
            if not args:
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Call) and _call_name(node)[1] in PATH_SINKS:
                    if any(_uses(a, args) for a in list(node.args) + [k.value for k in node.keywords]):
                        problems.append(f"{path.relative_to(ROOT)}:{node.lineno}: {_call_name(node)[1]} "
                                        f"takes message content ({sorted(args)})")
    assert not problems, "\n".join(problems)


def test_the_scan_would_catch_them(tmp_path):
    """The scan itself: planted unsafe calls are found."""
    src = ("import yaml, pickle\nyaml.load(open('x'))\neval('1')\n"
           "def _on_msg(self, msg):\n    open(msg.header.frame_id, 'w')\n")
    tree = ast.parse(src)
    calls = {_call_name(n) for n in ast.walk(tree) if isinstance(n, ast.Call)}
    assert ("yaml", "load") in calls and ("", "eval") in calls
    fn = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef))
    sink = next(n for n in ast.walk(fn) if isinstance(n, ast.Call) and _call_name(n)[1] == "open")
    assert _uses(sink.args[0], {"msg"})
