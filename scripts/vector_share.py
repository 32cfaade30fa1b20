#!/usr/bin/env python3
"""How much of each hot function is SIMD: reads `objdump -d -C` of a release binary and
prints, per function, its instructions and the share that work on vector registers
(aarch64: NEON `vN.4s`/`qN`..., x86-64: `xmm`/`ymm`/`zmm`) and the vector float arithmetic.

    aarch64-linux-gnu-objdump -d -C --no-show-raw-insn groundwork | scripts/vector_share.py
    scripts/vector_share.py --min 'query::eval_run=0.5' ... < dump   # fail below a share

A scalar fallback shows as a share near 0. Used by .ci/aarch64 (docs/arm.md)."""
import argparse
import re
import sys

HOT = [
    "groundwork_core::query::eval_run",
    "groundwork_core::gmm::fit_segment_with",
    "groundwork_detect::detector::Detector::detect_on_pool",
    "groundwork_detect::bbox::min_area_rect",
]
NEON = re.compile(r"\bv\d+\.(?:16b|8b|8h|4h|4s|2s|2d|1d)\b|\bq\d+\b")
# Float arithmetic: NEON fadd/fmul/fmla..., x86 (v)addps/mulps/vfmadd...ps.
ARITH = re.compile(r"^(?:f(?:add|sub|mul|mla|mls|div|max|min)|v?(?:add|sub|mul|div|max|min)p[sd]|vfn?m(?:add|sub)\w*p[sd])$")


def is_vector(mnemonic, operands):
    """NEON: any operand in a vector arrangement. x86: 256/512-bit registers, or 128-bit
    ones in a packed instruction (scalar float also lives in xmm: vaddss, vmovsd... are not
    vector work)."""
    if NEON.search(operands):
        return True
    if re.search(r"%[yz]mm", operands):
        return True
    if "%xmm" in operands:
        return not re.search(r"s[sd]$|^v?cvt|^v?movs[sd]|^v?u?comis", mnemonic)
    return False


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--min", action="append", default=[], metavar="NAME=SHARE")
    args = ap.parse_args()
    floors = dict((k, float(v)) for k, v in (m.split("=") for m in args.min))
    stats = {}
    name = None
    for line in sys.stdin:
        m = re.match(r"^[0-9a-f]+ <(.*)>:$", line)
        if m:
            sym = m.group(1)
            name = next((h for h in HOT if sym == h or sym.startswith(h + "<")), None)
            continue
        if name is None or "\t" not in line:
            continue
        parts = line.split(":\t", 1)
        if len(parts) < 2 or not parts[1].strip():
            continue
        mnemonic, _, operands = parts[1].strip().replace("\t", " ").partition(" ")
        s = stats.setdefault(name, [0, 0, 0])
        s[0] += 1
        if is_vector(mnemonic, operands):
            s[1] += 1
            if ARITH.match(mnemonic):
                s[2] += 1
    failed = []
    print(f"{'function':55} {'instr':>6} {'vector':>7} {'share':>6} {'vec fp':>7}")
    for h in HOT:
        n, v, a = stats.get(h, [0, 0, 0])
        share = v / n if n else 0.0
        print(f"{h:55} {n:6} {v:7} {share:6.2f} {a:7}")
    for k, floor in floors.items():
        match = [h for h in HOT if h.endswith(k)]
        if not match:
            failed.append(f"{k}: not a hot function of this script")
            continue
        n, v, _ = stats.get(match[0], [0, 0, 0])
        if n == 0:
            failed.append(f"{k}: not in the binary (inlined or renamed?)")
        elif v / n < floor:
            failed.append(f"{k}: vector share {v / n:.2f} below {floor}")
    for f in failed:
        print("FAIL", f, file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
