"""The machine line that every benchmark and validation table ends with: a scaling table read
on another machine needs its processor, its cores and how many of them are physical."""

from __future__ import annotations

import os

from bayespsf._runtime import _cpu_name, machine, physical_cores


def _topology(root, siblings, name="core_cpus_list"):
    """A fake ``/sys/devices/system/cpu``: one folder per logical CPU, with the list of the
    hardware threads of its core (``siblings[cpu]``) in the file ``name``."""
    for cpu, threads in enumerate(siblings):
        folder = root / f"cpu{cpu}" / "topology"
        folder.mkdir(parents=True)
        (folder / name).write_text(f"{threads}\n")
        (folder / "core_id").write_text("0\n")  # repeats across dies: not used
    (root / "cpufreq").mkdir()  # not a CPU: not counted
    return root


def test_physical_cores_count_each_core_once(tmp_path):
    # four cores of two hardware threads each (CPU k and k + 4 share a core): 4 physical
    smt = [f"{k % 4},{k % 4 + 4}" for k in range(8)]
    assert physical_cores(_topology(tmp_path / "smt", smt)) == 4
    assert physical_cores(_topology(tmp_path / "plain", ["0", "1", "2"])) == 3
    older = _topology(tmp_path / "older", ["0-1", "0-1", "2-3", "2-3"], "thread_siblings_list")
    assert physical_cores(older) == 2


def test_physical_cores_are_unknown_where_the_topology_is_not_there(tmp_path):
    assert physical_cores(tmp_path / "absent") is None
    root = _topology(tmp_path / "part", ["0", "1"])
    (root / "cpu1" / "topology" / "core_cpus_list").unlink()
    assert physical_cores(root) is None


def test_the_processor_name_is_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: Fake\nmodel name\t: Fake CPU 9000 @ 3.0GHz\n")
    assert _cpu_name(info) == "Fake CPU 9000 @ 3.0GHz"
    info.write_text("processor\t: 0\n")
    assert _cpu_name(info) is None
    assert _cpu_name(tmp_path / "absent") is None


def test_the_machine_line_names_the_cores_and_the_physical_ones_where_fewer():
    line = machine()
    assert f", {os.cpu_count()} cores" in line and "Python " in line and "numpy " in line
    physical = physical_cores()
    assert (" physical)" in line) == bool(physical and physical < os.cpu_count())
