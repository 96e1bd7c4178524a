"""What this process may still take of its machine: memory and CPU cores, as the OS says.

    available_memory(jax.devices()[0])   # (bytes, where that figure comes from), or None
    usable_cores()

On a CPU the memory left is the least of the machine's MemAvailable (/proc/meminfo), what this
process's memory cgroups (v1 and v2, /sys/fs/cgroup) and their parents still admit, and what
its address-space limit (`ulimit -v`, RLIMIT_AS) leaves above its size (/proc/self/status);
on an accelerator, what its allocator says is free. `gst_jax.predict` sizes its programs by
it (docs/scaling.md). `size` writes a number of bytes as the one-line messages do.

Imports nothing of the package, and not jax: a device is read through its `platform` and
`memory_stats()`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import jax

CGROUP_ROOT = Path("/sys/fs/cgroup")
# cgroup v1 writes "no limit" as a huge number (PAGE_COUNTER_MAX pages).
NO_LIMIT = 2 ** 60


def available_memory(device: jax.Device) -> tuple[int, str] | None:
    """(bytes this process may still allocate on `device`, where that figure comes from), or
    None where unknown. A CPU: the least of the machine's MemAvailable, what is left under
    this process's cgroup limits and under its address-space limit (`ulimit -v`)."""
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" not in stats:
            return None
        return stats["bytes_limit"] - stats.get("bytes_in_use", 0), f"free on {device}"
    candidates = []
    if (meminfo := _read_kib("/proc/meminfo", "MemAvailable:")) is not None:
        candidates.append((meminfo, "MemAvailable of this machine"))
    try:
        proc_cgroup = Path("/proc/self/cgroup").read_text()
    except OSError:
        proc_cgroup = ""
    if headrooms := _cgroup_headrooms(proc_cgroup, CGROUP_ROOT):
        left, limit = min(headrooms)
        candidates.append((left, f"under this process's cgroup memory limit of {size(limit)}"))
    if (address_space := _address_space_left()) is not None:
        left, limit = address_space
        candidates.append((left, f"under this process's address-space limit of "
                                 f"{size(limit)}, ulimit -v"))
    return min(candidates) if candidates else None


def usable_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                                  # not Linux
        return os.cpu_count() or 1


def size(num_bytes: int) -> str:
    """"1.5 GiB", "256 MiB", "64 KiB", "12 bytes"."""
    for unit, power, digits in (("GiB", 30, 1), ("MiB", 20, 0), ("KiB", 10, 0)):
        if num_bytes >= 2 ** power:
            return f"{num_bytes / 2 ** power:.{digits}f} {unit}"
    return f"{max(num_bytes, 0)} bytes"


def _address_space_left() -> tuple[int, int] | None:
    """(what `ulimit -v` (RLIMIT_AS) leaves this process, the limit); None without one."""
    try:
        import resource  # POSIX only
    except ImportError:
        return None
    limit, _ = resource.getrlimit(resource.RLIMIT_AS)
    if limit == resource.RLIM_INFINITY:
        return None
    return limit - (_read_kib("/proc/self/status", "VmSize:") or 0), limit


def cgroup_headroom(proc_cgroup: str, root: Path) -> int | None:
    """What this process's memory cgroups (`/proc/self/cgroup` text, mounted at `root`) and
    their parents still admit: the least of limit - (usage - inactive file pages), which the
    kernel reclaims before it kills; None where no limit is set. cgroup v2 and v1."""
    headrooms = _cgroup_headrooms(proc_cgroup, root)
    return min(headrooms)[0] if headrooms else None


def _cgroup_headrooms(proc_cgroup: str, root: Path) -> list[tuple[int, int]]:
    """(headroom, limit) of every limited memory cgroup of this process and its parents."""
    headroom = []
    for line in proc_cgroup.splitlines():
        if line.count(":") < 2:
            continue
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            directory, files = root, ("memory.max", "memory.current", "inactive_file")
        elif "memory" in controllers.split(","):
            directory, files = root / "memory", ("memory.limit_in_bytes",
                                                 "memory.usage_in_bytes", "total_inactive_file")
        else:
            continue
        parts = [part for part in path.split("/") if part]
        for depth in range(len(parts), -1, -1):
            limit, usage, inactive = _cgroup_files(directory.joinpath(*parts[:depth]), files)
            if limit is not None and usage is not None and limit < NO_LIMIT:
                headroom.append((limit - usage + (inactive or 0), limit))
    return headroom


def _cgroup_files(directory: Path, files: tuple[str, str, str]):
    """(limit, usage, inactive file bytes) of one cgroup directory; None for what is absent."""
    limit_file, usage_file, inactive_key = files

    def number(name):
        try:
            text = (directory / name).read_text().strip()
        except OSError:
            return None
        return NO_LIMIT if text == "max" else int(text)

    inactive = None
    try:
        for line in (directory / "memory.stat").read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == inactive_key:
                inactive = int(value)
    except OSError:
        pass
    return number(limit_file), number(usage_file), inactive


def _read_kib(path: str, field: str) -> int | None:
    """A `field: N kB` line of a /proc file, in bytes."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None
