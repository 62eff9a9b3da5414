"""Which processes hold a device path open: what a "busy" error names, on both the serial and USB paths."""

from __future__ import annotations

import os


def _proc_cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode("utf-8", "replace").strip()
    except OSError:
        return ""


def find_holders(path: str) -> list[tuple[int, str]]:
    """Processes holding ``path``: first the one that took its ``flock`` (``/proc/locks``), then every
    other process with it open (``/proc/*/fd``); ``(pid, command line)`` each.
    Empty where ``/proc`` is not there (the error then names the device only)."""
    try:
        st = os.stat(path)
        real = os.path.realpath(path)
    except OSError:
        return []
    key = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    pids: list[int] = []
    try:
        with open("/proc/locks", encoding="ascii", errors="replace") as f:
            for line in f:
                parts = line.split()
                if len(parts) >= 6 and parts[1] == "FLOCK" and parts[5] == key and parts[4].isdigit():
                    pids.append(int(parts[4]))
    except OSError:
        pass
    try:
        entries = os.listdir("/proc")
    except OSError:
        entries = []
    for entry in entries:
        if not entry.isdigit() or int(entry) in pids:
            continue
        try:
            fds = os.listdir(f"/proc/{entry}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                if os.readlink(f"/proc/{entry}/fd/{fd}") == real:
                    pids.append(int(entry))
                    break
            except OSError:
                continue
    return [(pid, _proc_cmdline(pid)) for pid in dict.fromkeys(pids) if os.path.exists(f"/proc/{pid}")]


__all__ = ["find_holders"]
