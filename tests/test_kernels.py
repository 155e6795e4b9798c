"""Nothing compiles inside the loop: every kernel a run calls is ready before its clock starts."""

import sys

from numba.core.registry import CPUDispatcher

from maglev_haptics.diagrams.application import BuildDiagram
from maglev_haptics.diagrams.runner import simulate
from maglev_haptics.diagrams.scenario import load_scenario
from maglev_haptics.hardware.kernels import compile_kernels, declared_kernels


def compiled_versions():
    """{kernel name: the argument types it is compiled for} over the imported package."""
    versions = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("maglev_haptics"):
            continue
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.__module__ == module_name:
                versions[f"{module_name}.{name}"] = set(value.overloads)
    return versions


def test_runs_compile_nothing_after_the_kernels_are_ready():
    # Levitation, rigid contact with the hand, the lattice on its worker thread, and the
    # stereo display's views.
    builts = [BuildDiagram(load_scenario(name)) for name in
              ("levitate", "peg_in_hole", "deformable_surface", "stereo_display")]
    compile_kernels(progress=False)
    before = compiled_versions()
    assert all(signature in kernel.overloads for kernel, signature in declared_kernels())
    for built, duration_s in zip(builts, (1.0, 3.0, 1.5, 1.2)):
        simulate(built, duration_s, progress=False)
    after = compiled_versions()
    compiled_in_loop = {name: versions - before.get(name, set())
                        for name, versions in after.items()
                        if versions - before.get(name, set())}
    assert compiled_in_loop == {}
