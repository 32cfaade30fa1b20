"""groundwork: LiDAR ground segmentation and object proposals from numpy (the API and its
documentation: __init__.pyi, docs/python.md).

The native module is built for x86-64-v3 (AVX2, FMA, BMI1/2, F16C, LZCNT, MOVBE) on x86-64:
on an older CPU its first vectorised instruction would kill the interpreter with SIGILL, so
the CPU is checked here, in plain Python, before it is loaded."""


# x86-64-v3's features as the native binary's own check names them: (name, cpuid leaf,
# register, bit).
_X86_64_V3 = [
    ("avx", 1, 2, 28), ("osxsave", 1, 2, 27), ("avx2", 7, 1, 5), ("fma", 1, 2, 12),
    ("bmi1", 7, 1, 3), ("bmi2", 7, 1, 8), ("f16c", 1, 2, 29), ("movbe", 1, 2, 22),
    ("lzcnt", 0x80000001, 2, 5),
]
# cpuid(leaf=edi, subleaf=esi) -> out[0..4] = eax, ebx, ecx, edx (System V calling convention):
# push rbx; mov eax, edi; mov ecx, esi; mov r8, rdx; cpuid; mov [r8], eax; mov [r8+4], ebx;
# mov [r8+8], ecx; mov [r8+12], edx; pop rbx; ret
_CPUID = bytes.fromhex("53 89f8 89f1 4989d0 0fa2 418900 41895804 41894808 4189500c 5b c3")


def _cpuid_registers():
    """{leaf: (eax, ebx, ecx, edx)} for the leaves the check needs, by running `cpuid` (the
    instruction itself: what the CPU, or an emulator's CPU, says), or None where executable
    memory is refused."""
    import ctypes
    import mmap

    try:
        page = mmap.mmap(-1, mmap.PAGESIZE, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    except (OSError, AttributeError, ValueError):
        return None
    try:
        page.write(_CPUID)
        anchor = ctypes.c_char.from_buffer(page)
        fn = ctypes.CFUNCTYPE(None, ctypes.c_uint32, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint32 * 4))(
            ctypes.addressof(anchor)
        )
        out = (ctypes.c_uint32 * 4)()
        regs = {}
        fn(0, 0, out)
        max_leaf = out[0]
        fn(0x80000000, 0, out)
        max_ext = out[0]
        for leaf in (1, 7, 0x80000001):
            if leaf <= max_leaf or (leaf >= 0x80000000 and leaf <= max_ext):
                fn(leaf, 0, out)
                regs[leaf] = tuple(out)
            else:
                regs[leaf] = (0, 0, 0, 0)
        del fn, anchor
        return regs
    finally:
        page.close()


def _missing_cpu_features() -> list[str]:
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64"):
        return []  # aarch64: Armv8-A with NEON, which every 64-bit Arm Linux CPU has
    regs = _cpuid_registers()
    if regs is not None:
        return [name for name, leaf, reg, bit in _X86_64_V3 if not regs[leaf][reg] >> bit & 1]
    # No executable memory (a hardened kernel): the kernel's list, where it has one (it
    # drops avx where it does not save the AVX registers; lzcnt is listed as abm).
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            flags = next((ln.split(":", 1)[1].split() for ln in f if ln.startswith("flags")), None)
    except OSError:
        return []
    if flags is None:
        return []
    names = {"lzcnt": "abm", "osxsave": "avx"}
    return [n for n, *_ in _X86_64_V3 if names.get(n, n) not in flags]


_missing = _missing_cpu_features()
if _missing:
    raise ImportError(
        f"groundwork: this CPU lacks {' '.join(_missing)}, which this build uses (it targets "
        "x86-64-v3: Intel Haswell, AMD Zen 1 or later). Build for this CPU: "
        "RUSTFLAGS='-C target-cpu=native' pip install ./crates/groundwork-py"
    )

from groundwork._native import *  # noqa: E402,F403
from groundwork._native import __version__  # noqa: E402,F401
