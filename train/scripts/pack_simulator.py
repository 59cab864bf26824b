"""Pack the simulator for a training machine that has no gelstereo build (a rented GPU box).

    cd train && ../.venv/bin/python scripts/pack_simulator.py --out ../.gpu/simulator.tar.xz

Builds `simulate_split` (`crates/gelstereo-sim/examples`: `gelstereo simulate`'s dataset writer
alone), strips it and packs it with the shared libraries it loads beyond the C library: OpenCV's
core, imgproc and imgcodecs and theirs, ~9 MB as .tar.xz. OpenCV's imgcodecs also links GDAL, GDCM
and OpenEXR for formats the simulator never reads or writes (it writes PNG and round-trips JPEG);
with their own libraries they would add ~200 MB, so the archive holds stubs of them instead: the
functions OpenCV calls while loading (`GDALAllRegister`, constructors of its codec objects) do
nothing, any other aborts. Before packing, the script checks that the packed binary resolves every
library inside the archive and writes, byte for byte, what the build it came from writes.
On the target (a glibc no older than this machine's):

    mkdir S && tar -C S -xJf simulator.tar.xz
    LD_LIBRARY_PATH=S/lib S/simulate_split OUT 950 4 101 wide train   # as gelstereo simulate --split train
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = "simulate_split"
# The C library's parts: every target machine has its own, matched to its kernel and loader.
SYSTEM = {"libc.so.6", "libm.so.6", "libpthread.so.0", "libdl.so.2", "librt.so.1", "ld-linux-x86-64.so.2"}
# Codec back-ends of OpenCV's imgcodecs that the simulator never uses.
STUBBED = re.compile(r"^lib(gdal|gdcm[A-Za-z]*|OpenEXR[-0-9_]*)\.so")
# What OpenCV calls from those libraries while it loads (codec registration, static objects).
CALLED_AT_LOAD = re.compile(r"^GDALAllRegister$|C[12]E")


def run(*cmd: str, **kw) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw).stdout


def needed(path: Path) -> list[str]:
    return re.findall(r"\(NEEDED\).*\[(.*)\]", run("readelf", "-d", str(path)))


def resolved(binary: Path, env: dict | None = None) -> dict[str, str]:
    """`ldd`'s name -> path of every library `binary` loads ("not found" where none)."""
    out = run("ldd", str(binary), env=env)
    return {m[0]: m[1] for m in re.findall(r"^\s*(\S+) => (\S+)", out, re.M)}


def dynamic_symbols(path: Path, defined: bool) -> set[str]:
    flag = "--defined-only" if defined else "--undefined-only"
    names = set()
    for line in run("nm", "-D", flag, str(path)).splitlines():
        parts = line.split()
        if not parts or (not defined and parts[0] == "w") or (defined and parts[-2] in ("U", "w")):
            continue
        names.add(parts[-1].split("@")[0])
    return names


def closure(binary: Path, paths: dict[str, str]) -> tuple[dict[str, Path], set[str]]:
    """The libraries to carry (name -> path) and the names of those to stub, walking NEEDED entries
    from `binary` and not into the C library or the stubbed ones; `paths`: `resolved(binary)`."""
    carry: dict[str, Path] = {}
    stubs: set[str] = set()
    todo = needed(binary)
    while todo:
        name = todo.pop()
        if name in carry or name in stubs or name in SYSTEM:
            continue
        if STUBBED.match(name):
            stubs.add(name)
            continue
        if name not in paths or paths[name] == "not":
            raise SystemExit(f"{binary}: library {name} not found on this machine")
        carry[name] = Path(paths[name])
        todo += needed(carry[name])
    return carry, stubs


def write_stubs(carry: dict[str, Path], binary: Path, paths: dict[str, str], stubs: set[str], lib: Path,
                work: Path) -> int:
    """One stub library per stubbed name, defining every symbol the carried files take from them;
    `paths`: `resolved(binary)`, where the C library's parts are."""
    defined = set().union(*(dynamic_symbols(Path(paths[n]), True) for n in SYSTEM if n in paths))
    defined |= set().union(*(dynamic_symbols(p, True) for p in carry.values()))
    wanted = dynamic_symbols(binary, False).union(*(dynamic_symbols(p, False) for p in carry.values()))
    missing = sorted(wanted - defined)
    source = work / "stub.c"
    body = ["#include <stdlib.h>"]
    body += [f"void {s}(void) {{ }}" if CALLED_AT_LOAD.search(s) else f"void {s}(void) {{ abort(); }}"
             for s in missing]
    source.write_text("\n".join(body) + "\n")
    for name in sorted(stubs):
        run("gcc", "-shared", "-fPIC", "-O1", "-o", str(lib / name), str(source), f"-Wl,-soname,{name}")
    return len(missing)


def check(pack: Path, built: Path, work: Path) -> None:
    """Every library of the packed binary resolves inside the pack, and a small dataset comes out as
    the build writes it."""
    env = {"LD_LIBRARY_PATH": str(pack / "lib"), "PATH": "/usr/bin:/bin"}
    outside = {n: p for n, p in resolved(pack / EXAMPLE, env).items()
               if n not in SYSTEM and not p.startswith(str(pack / "lib"))}
    if outside:
        raise SystemExit(f"packed {EXAMPLE} loads libraries from outside the pack: {outside}")
    args = ["3", "2", "5", "wide", "train"]
    subprocess.run([str(pack / EXAMPLE), str(work / "packed"), *args], check=True, env=env)
    subprocess.run([str(built), str(work / "built"), *args], check=True)
    files = {side: sorted(f.relative_to(work / side) for f in (work / side).rglob("*") if f.is_file())
             for side in ("packed", "built")}
    if files["packed"] != files["built"] or not files["built"] or any(
            (work / "packed" / f).read_bytes() != (work / "built" / f).read_bytes() for f in files["built"]):
        raise SystemExit("the packed simulator's dataset differs from the build's")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="archive to write (.tar.xz)")
    args = p.parse_args(argv)
    missing = [t for t in ("cargo", "readelf", "nm", "ldd", "strip", "gcc") if shutil.which(t) is None]
    if missing:
        raise SystemExit(f"pack_simulator needs {', '.join(missing)} on PATH (binutils, gcc, cargo)")
    subprocess.run(["cargo", "build", "--release", "-q", "-p", "gelstereo-sim", "--example", EXAMPLE],
                   check=True, cwd=REPO)
    built = REPO / "target" / "release" / "examples" / EXAMPLE
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pack = work / "pack"
        (pack / "lib").mkdir(parents=True)
        shutil.copy(built, pack / EXAMPLE)
        run("strip", str(pack / EXAMPLE))
        paths = resolved(built)
        carry, stubs = closure(built, paths)
        for name, path in carry.items():
            shutil.copy(path, pack / "lib" / name)
        stubbed_symbols = write_stubs(carry, built, paths, stubs, pack / "lib", work)
        check(pack, built, work)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        part = args.out.with_name(args.out.name + ".part")
        with tarfile.open(part, "w:xz") as tar:
            for f in sorted(pack.rglob("*")):
                tar.add(f, arcname=str(f.relative_to(pack)), recursive=False)
        part.replace(args.out)
    print(f"{args.out}: {EXAMPLE} with {len(carry)} libraries and {len(stubs)} stubs ({stubbed_symbols} "
          f"symbols), {args.out.stat().st_size / 1e6:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
