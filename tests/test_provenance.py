"""The code hashes that make an edit rerun its jobs: the package's import graph, read from the sources,
against what Python really loads."""

import json
import os
import re
import subprocess
import sys

import pytest

from newdyn import cli, effects, provenance


def loaded_by_importing(module: str) -> set[str]:
    """The package's modules a fresh interpreter holds after importing ``newdyn.<module>``, but the effect library's
    files, which the registry loads and a job's hash takes as files."""
    code = f"import importlib, json, sys; importlib.import_module('newdyn.{module}'); print(json.dumps(sorted(sys.modules)))"
    names = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    return {name.removeprefix("newdyn.") if name != "newdyn" else provenance.ROOT
            for name in names if (name == "newdyn" or name.startswith("newdyn.")) and not name.startswith("newdyn.effects.library")}


@pytest.mark.parametrize("module", ["cli", "diagnosis", "hidden", "plots", "calibration", "mcmc_calibration"])
def test_the_import_graph_holds_every_module_python_loads(module):
    assert loaded_by_importing(module) <= set(provenance.imported(module))


def test_every_command_of_the_cli_has_its_modules(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    commands = re.search(r"\{([a-z,-]+)\}", capsys.readouterr().out).group(1).split(",")
    for command in commands:
        assert {"cli", "config"} <= set(provenance.command_modules(command))
    with pytest.raises(ValueError, match="no command 'nope'"):
        provenance.command_modules("nope")


def test_a_command_depends_on_what_its_function_imports_and_no_more():
    simulate, plot, diagnose = (set(provenance.command_modules(c)) for c in ("simulate", "plot", "diagnose"))
    assert {"simulation", "kernels", "kernel_template"} <= simulate  # the kernel's template is read, not imported
    assert not simulate & {"diagnosis", "plots", "likelihood", "noise"}
    assert "plots" in plot and not plot & {"simulation", "diagnosis"}
    # imported inside a function, and the forms a registry loads by listing its folder
    assert {"model_comparison", "discovery.forms.periodic"} <= diagnose
    # the blind test's generator reads the verdicts' names without importing the diagnosis
    assert "diagnosis" not in provenance.command_modules("hidden-measurement")


def test_an_effect_file_brings_its_own_imports():
    loose = effects.active()["loose_bearing"].source
    assert "effects.contact" not in provenance.command_modules("simulate")
    assert provenance.command_hash("simulate", [loose]) != provenance.source_hash(*provenance.command_modules("simulate"), files=[loose])


def test_command_hashes_are_remembered_for_the_exact_package(tmp_path):
    """A later process (the next parse, a cluster job) takes a command's hash from the cache folder, under the hash
    of the package's files, without reading the import graph; an unreadable remembered file is computed again."""
    environment = {**os.environ, "NEWDYN_CACHE": str(tmp_path)}
    hashes = "from newdyn import provenance; print(provenance.command_hash('simulate'), provenance.command_hash('plot'))"
    no_graph = "from newdyn import provenance; provenance._command_hash = None; " + hashes.split("; ", 1)[1]

    def run(code):
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=environment).stdout

    computed = run(hashes)
    assert computed.split() == [provenance.command_hash("simulate"), provenance.command_hash("plot")]
    assert run(no_graph) == computed
    for remembered in (tmp_path / "code-hashes").glob("*.json"):
        remembered.write_text("{not json")
    assert run(hashes) == computed
