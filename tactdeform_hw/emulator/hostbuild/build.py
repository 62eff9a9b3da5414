"""Build a PlatformIO firmware tree into a shared library for the host, against the package's shim.

The tree is the PlatformIO layout the eTactileKit firmware uses: ``src/*.cpp``, libraries in
``lib/<name>/`` (sources beside the headers, or in ``lib/<name>/src/``) and an optional ``include/``.  It is
compiled with the system C++ compiler (C++17, ``-fPIC -shared``) together with the shim's runtime, with
the shim's headers first on the include path (so ``<Arduino.h>`` is ours, not a board's), then
``include/`` and every library folder.  A header the tree git-ignores and ships as ``<name>.example``
(v2's ``lib/Configuration/configuration.h``) is taken from the example.

The result is cached under ``$TACTDEFORM_HW_CACHE`` (or ``~/.cache/tactdeform_hw/firmware/``) by a hash
of everything that decides the binary: the tree's sources, the shim, the compiler's identity and version,
the flags and the generated accessor unit.  A second build of the same tree is a file lookup.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from tactdeform_hw.emulator.hostbuild.statemap import Register, StateMap
from tactdeform_hw.errors import ConfigurationError, FirmwareBuildError

SHIM_DIR = Path(__file__).resolve().parent / "shim"
RUNTIME_SOURCE = SHIM_DIR / "hostbuild_runtime.cpp"

DEFAULT_DEFINES: dict[str, str] = {"ETACTILEKIT_COMPACT_BOARD": "", "SERIAL_COMMUNICATION": ""}
"""The upstream configuration's defaults; defined empty, as the firmware's own ``#define`` does, so the
firmware redefining them is no warning."""

BASE_FLAGS: tuple[str, ...] = ("-std=gnu++17", "-O1", "-fPIC", "-shared", "-w")
COMPILERS: tuple[str, ...] = ("c++", "g++", "clang++")
_SOURCE_EXT = (".cpp", ".cc", ".cxx", ".c")
_TREE_EXT = (*_SOURCE_EXT, ".h", ".hpp", ".hh", ".inc", ".example")
_ERROR = re.compile(r"^(?P<file>[^\s:][^:]*):(?P<line>\d+):(?:(?P<col>\d+):)? (?:fatal )?error: (?P<msg>.*)$")
_UNDEFINED = re.compile(r"undefined (?:reference to|symbol[s]?:?) [`'\"]?(?P<sym>[^'`\"\n]+)")


def cache_dir() -> Path:
    """Where built firmware is kept: ``$TACTDEFORM_HW_CACHE`` or ``~/.cache/tactdeform_hw/firmware``."""
    env = os.environ.get("TACTDEFORM_HW_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "tactdeform_hw" / "firmware"


def find_compiler(preferred: str | None = None) -> str:
    """The C++ compiler: ``preferred`` (which must exist), else ``$CXX``, ``c++``, ``g++``, ``clang++``."""
    if preferred is not None:
        found = shutil.which(preferred)
        if not found:
            raise FirmwareBuildError(f"compiler={preferred!r} is not on PATH; nothing was built")
        return found
    candidates = [c for c in (os.environ.get("CXX"),) if c] + list(COMPILERS)
    for name in candidates:
        found = shutil.which(name)
        if found:
            return found
    hint = {
        "linux": "install one: apt install g++ (Debian/Ubuntu) or dnf install gcc-c++ (Fedora)",
        "darwin": "install Xcode's command line tools: xcode-select --install",
    }.get(sys.platform, "install a C++17 compiler (g++ or clang++) and put it on PATH")
    raise FirmwareBuildError(
        "building firmware on the host needs a C++ compiler, and none of "
        f"{', '.join(candidates)} is on PATH (set $CXX to use another): {hint}"
    )


def compiler_identity(compiler: str) -> str:
    """The compiler's path and ``--version`` (part of every build's cache key); asked once per compiler
    binary and process, as each emulator made looks its build up again."""
    try:
        st = os.stat(compiler)
    except OSError as exc:
        raise FirmwareBuildError(f"the C++ compiler {compiler} does not run: {exc}") from exc
    return _identity(compiler, os.path.realpath(compiler), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=16)
def _identity(compiler: str, real: str, mtime_ns: int, size: int) -> str:
    try:
        out = subprocess.run([compiler, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FirmwareBuildError(f"the C++ compiler {compiler} does not run: {exc}") from exc
    return f"{compiler}\n{out.stdout.strip()}"


@dataclass(frozen=True)
class BuildResult:
    """A built firmware: the shared library, and what it was built from."""

    library: Path
    key: str
    cached: bool
    seconds: float
    compiler: str
    registers: tuple[Register, ...] = field(default_factory=tuple)


def _tree_files(tree: Path) -> list[Path]:
    files: list[Path] = []
    for sub in ("src", "lib", "include"):
        base = tree / sub
        if base.is_dir():
            files += [p for p in base.rglob("*") if p.is_file() and p.name.endswith(_TREE_EXT)]
    return sorted(files)


def _sources(tree: Path) -> list[Path]:
    srcs = [p for p in (tree / "src").glob("*") if p.suffix in _SOURCE_EXT]
    lib = tree / "lib"
    if lib.is_dir():
        for d in sorted(p for p in lib.iterdir() if p.is_dir()):
            srcs += [p for p in d.glob("*") if p.suffix in _SOURCE_EXT]
            srcs += [p for p in (d / "src").glob("*") if p.suffix in _SOURCE_EXT]
    return sorted(srcs)


def _include_dirs(tree: Path) -> list[Path]:
    dirs = [tree / "include"] if (tree / "include").is_dir() else []
    lib = tree / "lib"
    if lib.is_dir():
        for d in sorted(p for p in lib.iterdir() if p.is_dir()):
            dirs.append(d)
            if (d / "src").is_dir():
                dirs.append(d / "src")
    return dirs


def _examples(tree: Path) -> list[tuple[Path, Path]]:
    """Headers the tree ships only as ``<header>.example`` (git-ignored configuration)."""
    out = []
    for p in _tree_files(tree):
        if p.name.endswith(".h.example"):
            real = p.with_name(p.name[: -len(".example")])
            if not real.exists():
                out.append((p, real))
    return out


def _digest(parts: list[tuple[str, bytes]]) -> str:
    h = hashlib.sha256()
    for name, data in parts:
        h.update(name.encode())
        h.update(b"\0")
        h.update(hashlib.sha256(data).digest())
    return h.hexdigest()[:32]


@dataclass(frozen=True)
class _Plan:
    """Everything a build of one tree is made of."""

    root: Path
    sources: tuple[Path, ...]
    cxx: str
    ident: str
    flags: tuple[str, ...]
    unit: Path | None
    accessor: tuple[str, dict[int, str]] | None
    key_accessor: str  # the accessor as the tree names its unit: the same tree elsewhere is the same build
    registers: tuple[Register, ...]


def _plan(
    tree: str | os.PathLike[str],
    state_map: StateMap | None,
    defines: dict[str, str] | None,
    compiler: str | None,
    extra_flags: tuple[str, ...],
) -> _Plan:
    root = Path(tree).resolve()
    if not (root / "src").is_dir():
        raise ConfigurationError(
            f"firmware_src={str(tree)!r} is not a PlatformIO tree: it has no src/ folder"
        )
    sources = tuple(_sources(root))
    if not sources:
        raise ConfigurationError(f"firmware_src={str(tree)!r}: no C/C++ source in src/ or lib/*/")
    cxx = find_compiler(compiler)
    defs = dict(DEFAULT_DEFINES if defines is None else defines)
    flags = [*BASE_FLAGS, *(f"-D{k}={v}" for k, v in sorted(defs.items())), *extra_flags]
    if sys.platform.startswith("linux"):
        flags.append("-Wl,-z,defs")  # an undefined symbol is a build error, not a load error
    if state_map is None:
        return _Plan(root, sources, cxx, compiler_identity(cxx), tuple(flags), None, None, "", ())
    unit = (root / state_map.unit).resolve()
    if unit not in [s.resolve() for s in sources]:
        raise ConfigurationError(
            f"state map unit={state_map.unit!r} is not one of the tree's sources "
            f"({', '.join(str(s.relative_to(root)) for s in sources)})"
        )
    return _Plan(
        root,
        sources,
        cxx,
        compiler_identity(cxx),
        tuple(flags),
        unit,
        state_map.accessor_source(unit),
        state_map.accessor_source(Path(state_map.unit))[0],
        tuple(state_map.parsed()),
    )


def _shim_parts() -> list[tuple[str, bytes]]:
    return [
        ("shim/" + str(p.relative_to(SHIM_DIR)), p.read_bytes())
        for p in sorted(SHIM_DIR.rglob("*"))
        if p.is_file()
    ]


def _key(plan: _Plan) -> str:
    parts = [(str(p.relative_to(plan.root)), p.read_bytes()) for p in _tree_files(plan.root)]
    parts += _shim_parts()
    parts += [("compiler", plan.ident.encode()), ("flags", "\0".join(plan.flags).encode())]
    parts.append(("accessor", plan.key_accessor.encode()))
    return _digest(parts)


_SEEN: dict[tuple[object, ...], BuildResult] = {}
"""Builds this process already looked up, by :func:`_stat_key`: a campaign that makes an emulator per run
finds its build without hashing the tree each time."""


def _stat_key(
    tree: str | os.PathLike[str],
    state_map: StateMap | None,
    defines: dict[str, str] | None,
    compiler: str | None,
    extra_flags: tuple[str, ...],
    where: Path,
) -> tuple[object, ...]:
    """Everything a build depends on, with the tree's and the shim's files by name, size and modification
    time (any edit changes it) and the compiler's environment; the content hash is taken when it changes."""
    root = Path(tree).resolve()
    files = [*_tree_files(root), *(p for p in sorted(SHIM_DIR.rglob("*")) if p.is_file())]
    stats = tuple((str(p), st.st_size, st.st_mtime_ns) for p in files for st in (p.stat(),))
    return (
        root,
        stats,
        None
        if state_map is None
        else (state_map.unit, tuple(state_map.registers.items()), state_map.firmware),
        tuple(sorted((defines or {}).items())) if defines is not None else None,
        compiler,
        os.environ.get("CXX"),
        os.environ.get("PATH"),
        extra_flags,
        where.resolve(),
    )


def build(
    tree: str | os.PathLike[str],
    *,
    state_map: StateMap | None = None,
    defines: dict[str, str] | None = None,
    compiler: str | None = None,
    extra_flags: tuple[str, ...] = (),
    cache: str | os.PathLike[str] | None = None,
) -> BuildResult:
    """Build ``tree`` (cached).  Raises :class:`FirmwareBuildError` naming the file and line of the first
    compiler error, or the undefined symbol at link time."""
    t0 = time.perf_counter()
    where = Path(cache) if cache is not None else cache_dir()
    tree_key = _stat_key(tree, state_map, defines, compiler, extra_flags, where)
    seen = _SEEN.get(tree_key)
    if seen is not None and seen.library.is_file():
        return dataclasses.replace(seen, cached=True, seconds=time.perf_counter() - t0)
    plan = _plan(tree, state_map, defines, compiler, extra_flags)
    key = _key(plan)
    lib_path = where / f"{key}.so"
    if lib_path.is_file():
        found = BuildResult(lib_path, key, True, time.perf_counter() - t0, plan.cxx, plan.registers)
        _SEEN[tree_key] = found
        return found
    where.mkdir(parents=True, exist_ok=True)
    _compile(plan, where, lib_path)
    meta = {
        "tree": str(plan.root),
        "compiler": plan.ident,
        "flags": plan.flags,
        "built_s": time.perf_counter() - t0,
    }
    (where / f"{key}.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    made = BuildResult(lib_path, key, False, time.perf_counter() - t0, plan.cxx, plan.registers)
    _SEEN[tree_key] = made
    return made


def _compile(plan: _Plan, where: Path, lib_path: Path) -> None:
    """Compile the tree (the accessor unit in place of the mapped one) and link it with the runtime."""
    with tempfile.TemporaryDirectory(prefix="hostbuild-") as tmp:
        work = Path(tmp)
        overlay = work / "overlay"
        overlay.mkdir()
        for example, real in _examples(plan.root):
            shutil.copyfile(example, overlay / real.name)
        units = [str(s) for s in plan.sources if plan.unit is None or s.resolve() != plan.unit]
        acc_file = work / "hostbuild_state.cpp"
        if plan.accessor is not None:
            acc_file.write_text(plan.accessor[0], encoding="utf-8")
            units.append(str(acc_file))
        out = work / "firmware.so"
        runtime = _runtime_object(plan.cxx, plan.ident, list(plan.flags), where)
        cmd = [
            plan.cxx,
            *plan.flags,
            f"-I{SHIM_DIR}",
            f"-I{overlay}",
            *(f"-I{d}" for d in _include_dirs(plan.root)),
            *units,
            str(runtime),
            "-o",
            str(out),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            raise _build_error(proc.stderr, plan.root, acc_file, plan.accessor[1] if plan.accessor else {})
        tmp_lib = where / f".{lib_path.name}.{os.getpid()}.tmp"
        shutil.copyfile(out, tmp_lib)
        os.replace(tmp_lib, lib_path)


def _runtime_object(cxx: str, ident: str, flags: list[str], where: Path) -> Path:
    """The shim's runtime, compiled once per shim, compiler and flags (the bulk of a cold build)."""
    cflags = [f for f in flags if f != "-shared" and not f.startswith("-Wl,")]
    parts = _shim_parts() + [("compiler", ident.encode()), ("flags", "\0".join(cflags).encode())]
    obj = where / f"runtime-{_digest(parts)}.o"
    if obj.is_file():
        return obj
    tmp = where / f".{obj.name}.{os.getpid()}.tmp.o"
    proc = subprocess.run(
        [cxx, *cflags, f"-I{SHIM_DIR}", "-c", str(RUNTIME_SOURCE), "-o", str(tmp)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        raise FirmwareBuildError(f"the shim's runtime does not compile with {cxx}:\n{_tail(proc.stderr)}")
    os.replace(tmp, obj)
    return obj


def _build_error(stderr: str, root: Path, acc_file: Path, acc_lines: dict[int, str]) -> FirmwareBuildError:
    """The first ``file:line:col: error:`` of the compiler's output, in the firmware's terms."""
    for raw in stderr.splitlines():
        m = _ERROR.match(raw.strip())
        if not m:
            continue
        file, line, msg = m.group("file"), int(m.group("line")), m.group("msg")
        path = Path(file)
        if path.resolve() == acc_file.resolve():
            reg = acc_lines.get(line, "?")
            return FirmwareBuildError(
                f"state map: register {reg!r} does not name a variable the firmware unit can read: {msg}"
            )
        try:
            shown = str(path.resolve().relative_to(root))
        except ValueError:
            shown = file
        return FirmwareBuildError(
            f"the firmware does not compile on the host: {shown}:{line}: error: {msg}\n{_tail(stderr)}",
            file=shown,
            line=line,
        )
    m2 = _UNDEFINED.search(stderr)
    if m2:
        return FirmwareBuildError(
            f"the firmware does not link on the host: undefined symbol {m2.group('sym').strip()} "
            "(a function the firmware declares but never defines, or a platform function the shim does not "
            f"provide: see docs/firmware-host-build.md, 'Adding a shim function')\n{_tail(stderr)}"
        )
    return FirmwareBuildError(f"the firmware does not build on the host:\n{_tail(stderr)}")


def _tail(text: str, lines: int = 12) -> str:
    return "\n".join(text.strip().splitlines()[:lines])
