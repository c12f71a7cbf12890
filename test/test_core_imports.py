"""The science core and the message conversion import and run without rclpy, and the
core imports nothing of the package outside itself."""

import subprocess
import sys
from pathlib import Path

import neurncd_ros

PKG = Path(neurncd_ros.__file__).parent

BLOCK_RCLPY = r"""
import importlib, pkgutil, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('rclpy', 'rosidl_runtime_py', 'sensor_msgs', 'std_msgs',
                                  'geometry_msgs', 'std_srvs'):
            raise ImportError('blocked for this test: ' + name)
sys.meta_path.insert(0, Block())
import neurncd_ros.core as core, neurncd_ros.core.msgconv
mods = [m.name for m in pkgutil.walk_packages(core.__path__, 'neurncd_ros.core.')]
for m in mods:
    importlib.import_module(m)
outside = sorted(k for k in sys.modules if k.startswith('neurncd_ros.')
                 and not k.startswith(('neurncd_ros.core', 'neurncd_ros.config')))
assert not outside, 'the core imports outside itself: ' + ', '.join(outside)
from neurncd_ros import config
config.default()
assert not any(k.split('.')[0] == 'rclpy' for k in sys.modules)
print(len(mods))
"""


def test_core_imports_without_rclpy():
    r = subprocess.run([sys.executable, "-c", BLOCK_RCLPY], capture_output=True, text=True,
                       timeout=300, cwd=PKG.parent)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.strip()) >= 15, "fewer core modules than expected were imported"


def _import_graph() -> dict[str, set[str]]:
    """Module -> package modules it imports (anywhere in its source, lazy imports too)."""
    import ast

    root = PKG.parent
    files = {}
    for path in PKG.rglob("*.py"):
        parts = list(path.relative_to(root).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        files[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)

    def owner(name: str) -> str:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name

    graph: dict[str, set[str]] = {}
    for mod, (path, is_pkg) in files.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = mod.split(".")[: len(mod.split(".")) - node.level + is_pkg]
                    base = ".".join(up + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base
                         for a in node.names]
            else:
                continue
            deps |= {owner(n) for n in names if n.startswith("neurncd_ros")}
        graph[mod] = deps - {mod, ""}
    return graph


def test_no_import_circles_and_the_core_imports_only_the_core():
    """Static: every import statement of the package, those inside functions included."""
    graph = _import_graph()
    assert len(graph) > 40 and "neurncd_ros.core.field.mapper" in graph
    outside = {m: sorted(d for d in deps if not d.startswith("neurncd_ros.core"))
               for m, deps in graph.items() if m.startswith("neurncd_ros.core")}
    assert not {m: d for m, d in outside.items() if d}, "the core imports outside itself"

    # Tarjan's strongly connected components: any with two or more modules is a circle.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while not comp or comp[-1] != v:
                comp.append(stack.pop())
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not circles, ("import circles (a backend imports register from "
                         "core.field.backends.registry, not the package): " + repr(circles))


def test_every_module_of_the_package_imports():
    """Nodes, tools, synth and core alike: a stale import anywhere fails here, not in use."""
    code = ("import importlib, pkgutil, neurncd_ros as p\n"
            "mods = [m.name for m in pkgutil.walk_packages(p.__path__, 'neurncd_ros.')]\n"
            "[importlib.import_module(m) for m in mods]\nprint(' '.join(mods))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, cwd=PKG.parent)
    assert r.returncode == 0, r.stderr
    assert set(r.stdout.split()) == set(_import_graph()) - {"neurncd_ros"}


def test_modules_over_500_lines_say_at_their_top_why_they_stay_one():
    import ast

    long = []
    for path in sorted(PKG.rglob("*.py")):
        text = path.read_text()
        if text.count("\n") <= 500:
            continue
        doc = " ".join((ast.get_docstring(ast.parse(text)) or "").split()).lower()
        if "one module" not in doc:
            long.append(str(path.relative_to(PKG)))
    assert not long, f"over 500 lines without a reason in the module docstring: {long}"


GLOBAL_SETTERS = {"torch.set_num_threads", "torch.set_num_interop_threads", "torch.manual_seed",
                  "torch.seed", "np.random.seed", "numpy.random.seed", "cv2.setNumThreads",
                  "random.seed"}
TORCH_DRAWS = {"rand", "randn", "randint", "randperm", "rand_like", "randn_like",
               "randint_like", "normal", "bernoulli", "multinomial", "poisson"}
TENSOR_DRAWS = {"uniform_", "normal_", "random_", "bernoulli_", "exponential_", "cauchy_",
                "geometric_", "log_normal_"}


def _dotted(node) -> str:
    import ast

    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        parts.append(node.id)
    return ".".join(reversed(parts))


def test_core_and_synth_set_no_process_state_and_draw_from_explicit_generators():
    """Thread counts and seeds belong to the executable; every draw names its generator.

    Allowed: a seed set inside ``with torch.random.fork_rng(...)`` (restored on exit).
    """
    import ast

    found = []
    for path in sorted([*(PKG / "core").rglob("*.py"), *(PKG / "synth").rglob("*.py")]):
        tree = ast.parse(path.read_text(), str(path))
        forked = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.With) and any(
                    isinstance(i.context_expr, ast.Call)
                    and _dotted(i.context_expr.func).endswith("random.fork_rng")
                    for i in node.items):
                forked |= {id(n) for n in ast.walk(node)}
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            name = _dotted(node.func)
            where = f"{path.relative_to(PKG)}:{node.lineno} {name}"
            kw = {k.arg for k in node.keywords}
            if name in GLOBAL_SETTERS and id(node) not in forked:
                found.append(where)
            elif name.startswith("torch.") and name.split(".")[-1] in TORCH_DRAWS \
                    and "generator" not in kw:
                found.append(where)
            elif name.startswith(("np.random.", "numpy.random.")) and name.split(".")[-1] \
                    not in ("default_rng", "Generator", "PCG64", "SeedSequence"):
                found.append(where)
            elif name.startswith("random.") and name != "random.Random":
                found.append(where)
            elif name.split(".")[-1] in TENSOR_DRAWS and "generator" not in kw:
                found.append(where)
    assert not found, f"process-wide state or global random draws: {found}"
