"""The renderer's structure: its import graph has no cycle, counting
imports inside functions too (three of them used to dodge a 21-module cycle
between the registry and every plugin), and the registry is a plain table
that the plugins never read back."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "renderer"


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the renderer modules it imports, anywhere in its body. `from
    .x import name` counts as an import of `x.name` when that is a module, else
    of `x`; the implicit import of a parent package does not count (every
    package's __init__ would otherwise close a cycle with its children)."""
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[:len(base) - node.level + 1]
                    stem = ".".join(base + ([node.module] if node.module else []))
                else:
                    stem = node.module or ""
                targets = [f"{stem}.{a.name}" if f"{stem}.{a.name}" in modules else stem
                           for a in node.names]
            for target in targets:
                while target and target not in modules:  # a name inside a module
                    target = target.rpartition(".")[0]
                if target and target != name:
                    graph[name].add(target)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test01_the_renderers_import_graph_is_acyclic():
    graph = import_graph()
    assert "renderer.registry" in graph and graph["renderer.integrators"], graph
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test02_the_cycle_finder_finds_a_cycle():
    # The check above is only as good as this: a cycle through a function-level
    # import is found.
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test03_the_registry_imports_no_plugin_and_no_plugin_reads_it_back():
    graph = import_graph()
    assert not {m for m in graph["renderer.registry"] if m.startswith("renderer.integrators")}
    for name, path in _modules().items():
        if name.startswith("renderer.integrators."):
            imported = {alias.name for node in ast.walk(ast.parse(path.read_text()))
                        if isinstance(node, ast.ImportFrom) and (node.module or "").endswith(
                            "registry") for alias in node.names}
            assert "METHODS" not in imported, f"{name} reads the registry's METHODS"


def test04_material_and_light_ids_are_defined_once():
    for stem in ("MAT_DIFFUSE", "LIGHT_POINT"):
        defined = [name for name, path in _modules().items()
                   if any(isinstance(n, ast.Assign) and any(
                       isinstance(t, (ast.Name, ast.Tuple)) and stem in ast.unparse(t)
                       for t in n.targets)
                       for n in ast.parse(path.read_text()).body)]
        assert len(defined) == 1, (stem, defined)


def test05_no_integrator_imports_another():
    graph = import_graph()
    integrators = {name for name, path in _modules().items()
                   if name.startswith("renderer.integrators.")
                   and "METHODS = (" in path.read_text()}
    assert {"renderer.integrators.path", "renderer.integrators.bdpt"} <= integrators
    for name in integrators:
        assert not graph[name] & integrators, (name, graph[name] & integrators)


def test06_test_helpers_live_in_tests():
    for name, path in _modules().items():
        text = path.read_text()
        for helper in ("def strategy_weights(", "def toy_chains("):
            assert helper not in text, f"{helper[4:-1]} is a test helper, in {name}"


def test07_no_renderer_file_is_over_about_600_lines():
    # Long files were where concepts piled up (BDPT's subpaths inside `bdpt`,
    # radiosity's solve inside its display): split by concept, not by size,
    # and this says when to look.
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text().splitlines())) > 650}
    assert not long, long


def test08_every_pixel_major_tile_loop_folds_and_stores_through_one_place():
    # The per-pixel fold and film store are renderer/kernels/tile.py's inline
    # kernels. (raster is sample-major: one z-buffer pass per sample over the
    # whole tile, so it accumulates whole blocks, still block by block.)
    modules = _modules()
    for name in ("renderer.integrators.path", "renderer.integrators.bdpt",
                 "renderer.integrators.radiosity", "renderer.kernels.photons"):
        text = modules[name].read_text()
        assert "add_sample(" in text and "store_pixel(" in text, name
    for name, path in modules.items():
        if name not in ("renderer.kernels.tile", "renderer.integrators.raster"):
            assert "out_w[row, c] =" not in path.read_text(), f"{name} stores a pixel itself"


def _calls(path: Path, function: str | None = None) -> set[str]:
    """Names called in a module (or in one of its functions)."""
    tree = ast.parse(path.read_text(), str(path))
    if function is not None:
        tree = next(node for node in ast.walk(tree)
                    if isinstance(node, ast.FunctionDef) and node.name == function)
    return {node.func.id for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)}


def test09_camera_side_specular_chains_take_one_step():
    """Path tracing, photon mapping's visible points and radiosity's display
    follow mirrors and glass through kernels/bsdf.specular_step, not each with
    its own copy of reflect / dielectric_sample (there were four)."""
    renderer = ROOT / PACKAGE
    for path, function in ((renderer / "integrators" / "path.py", None),
                           (renderer / "integrators" / "radiosity.py", None),
                           (renderer / "kernels" / "photons.py", "visible_point")):
        calls = _calls(path, function)
        assert "specular_step" in calls, path
        assert not calls & {"reflect", "dielectric_sample"}, (path, function)


_WARM_CHECK = r'''
import json
from numba.core.dispatcher import Dispatcher
from renderer import METHODS, RenderSpec, build_scene, resolve_document, warm_up
from renderer.runtime import run_plan

def signatures():
    import sys
    return {f"{name}.{key}": len(obj.signatures) for name, module in list(sys.modules.items())
            if name.startswith("renderer.") and module is not None
            for key, obj in vars(module).items() if isinstance(obj, Dispatcher)}

warm_up()
before = signatures()
scene = build_scene(resolve_document("cornell-box"))
for method in dict.fromkeys(METHODS.values()):
    for option in method.options:
        for choice in option.choices or ():
            run_plan(scene, RenderSpec(method=method.name, spp=2, depth=2, width=4, height=4,
                                       tile_size=4,
                                       options={**method.warm_base, option.name: choice}))
after = signatures()
print(json.dumps({k: [before.get(k, 0), n] for k, n in after.items() if n != before.get(k, 0)}))
'''


def test10_warm_up_leaves_no_option_to_compile_in_a_unit(tmp_path):
    """Every choice of every method's options renders with kernels that
    `warm_up` already compiled or loaded (Method.warm_options): a render
    process never compiles inside a unit. Photon's `photonmap` mode used to
    compile its k-NN kernel (38 s on 2 cores) in the first unit of such a job.
    In a fresh process, so kernels loaded by earlier tests do not count."""
    import json
    import os
    import subprocess
    import sys

    # A cache of radiosity solutions of its own: with a solution cached, the
    # warm-up needs no solver kernel, and the check would count loading one.
    env = {**os.environ, "RAYFARM_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", _WARM_CHECK], cwd=ROOT, capture_output=True,
                         text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    grown = json.loads(out.stdout.strip().splitlines()[-1])
    assert grown == {}, f"kernels first specialised after warm_up: {grown}"


_FEATURES_CHECK = '''
import json
import renderer  # noqa: F401 (sets Numba's code generator up)
from numba.core import codegen, config
print(json.dumps({"host": codegen.get_host_cpu_features(), "chosen": config.CPU_FEATURES}))
'''


def test11_avx512_code_uses_the_whole_register_unless_the_user_chose():
    """On a CPU with AVX-512 the renderer turns off LLVM's `prefer-256-bit`
    (set for Intel's cores, not AMD's), so the packet kernels' lane loops
    take zmm registers (renderer/kernels/__init__.py); elsewhere it changes
    nothing. A NUMBA_CPU_FEATURES the user set is left as it is. In fresh
    processes: the setting has to be made before anything compiles."""
    import json
    import os
    import subprocess
    import sys

    def chosen(extra_env: dict) -> dict:
        env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_CPU_")}
        out = subprocess.run([sys.executable, "-c", _FEATURES_CHECK], cwd=ROOT,
                             capture_output=True, text=True, timeout=300,
                             env={**env, **extra_env})
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    got = chosen({})
    if "+avx512f" in got["host"].split(","):
        assert got["chosen"] == got["host"] + ",-prefer-256-bit"
    else:
        assert got["chosen"] is None  # Numba's own choice: the host's features
    mine = got["host"] + ",+prefer-256-bit"
    assert chosen({"NUMBA_CPU_FEATURES": mine})["chosen"] == mine
