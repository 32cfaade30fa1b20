//! The CPU features the build relies on, checked when a binary starts.
//!
//! Release builds target x86-64-v3 (`.cargo/config.toml`): the compiler may use AVX2, FMA,
//! BMI1/2, F16C, LZCNT and MOVBE anywhere, so on an older CPU the first such instruction
//! kills the process with SIGILL and no message. Binaries call [`check`] first thing and
//! exit with a clear error instead. The check itself uses only `cpuid` and integer tests, so
//! it runs on any x86-64 CPU.
//!
//! Beyond that level, some loops have a second copy chosen at run time ([`avx512`]): the
//! multi-frame query's past components (`query::avx512`) and the PseudoLabeler's network
//! layers, in 512-bit registers where the CPU has AVX-512. Each copy does the same
//! operations per value as the portable one: the same bits either way.
//!
//! aarch64 builds target Armv8-A with NEON, which every 64-bit Arm Linux CPU has, so the
//! default build checks nothing. A build for a newer core (`-C target-cpu=cortex-a78ae` for
//! a Jetson Orin, docs/install.md) may use Armv8.1+ instructions an older core (Raspberry Pi
//! 4) lacks: the features it was compiled with are checked against the kernel's report.

/// The features the compiler was told it may use, by name, with how to test for them.
#[cfg(target_arch = "x86_64")]
const REQUIRED: [(&str, Feature); 9] = [
    ("avx", Feature::Leaf1Ecx(1 << 28)),
    // The OS must save the AVX registers on context switches (XSAVE enabled by the OS).
    ("osxsave", Feature::Leaf1Ecx(1 << 27)),
    ("avx2", Feature::Leaf7Ebx(1 << 5)),
    ("fma", Feature::Leaf1Ecx(1 << 12)),
    ("bmi1", Feature::Leaf7Ebx(1 << 3)),
    ("bmi2", Feature::Leaf7Ebx(1 << 8)),
    ("f16c", Feature::Leaf1Ecx(1 << 29)),
    ("movbe", Feature::Leaf1Ecx(1 << 22)),
    ("lzcnt", Feature::Ext1Ecx(1 << 5)),
];

#[cfg(target_arch = "x86_64")]
/// Register of a cpuid leaf and the feature's bit in it (as a mask: no variable shifts,
/// which the compiler would emit as BMI2's `shlx`).
#[derive(Clone, Copy)]
enum Feature {
    Leaf1Ecx(u32),
    Leaf7Ebx(u32),
    Ext1Ecx(u32),
}

/// Features beyond Armv8-A a build for a newer core may use, named once: `REQUIRED` (name,
/// whether this build was compiled to use it) and `detected()` (whether the kernel reports
/// it, in the same order). `is_aarch64_feature_detected!` takes only literals, hence a macro.
#[cfg(target_arch = "aarch64")]
macro_rules! beyond_armv8a {
    ($($f:tt),*) => {
        const REQUIRED: [(&str, bool); 9] = [$(($f, cfg!(target_feature = $f))),*];
        fn detected() -> [bool; 9] {
            [$(std::arch::is_aarch64_feature_detected!($f)),*]
        }
    };
}
#[cfg(target_arch = "aarch64")]
beyond_armv8a!(
    "lse", "rdm", "rcpc", "fp16", "dotprod", "crc", "aes", "sha2", "sve"
);

/// The CPU lacks features this build was compiled to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MissingCpuFeatures {
    /// Entry i set: the i-th required feature is missing.
    missing: [bool; 9],
}

impl std::fmt::Display for MissingCpuFeatures {
    // Runs on CPUs without AVX: plain indexed loop, barriers against vectorisation.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("this CPU lacks")?;
        #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
        for (i, (name, _)) in REQUIRED.iter().enumerate() {
            if std::hint::black_box(self.missing[i]) {
                f.write_str(" ")?;
                f.write_str(name)?;
            }
        }
        #[cfg(target_arch = "aarch64")]
        f.write_str(
            ", which this build uses (it was built for a newer Arm core; the default build \
             targets any Armv8-A CPU). Build for this CPU: RUSTFLAGS='-C target-cpu=native' \
             cargo build --release",
        )?;
        #[cfg(not(target_arch = "aarch64"))]
        f.write_str(
            ", which this build uses (it targets x86-64-v3: Intel Haswell, AMD Zen 1 or later). \
             Build for this CPU: RUSTFLAGS='-C target-cpu=native' cargo build --release",
        )?;
        Ok(())
    }
}

impl std::error::Error for MissingCpuFeatures {}

/// The environment variable that turns run-time CPU features off (comma-separated, e.g.
/// `avx512`), as NumPy's `NPY_DISABLE_CPU_FEATURES` does: to measure what a CPU without
/// them gets, on one that has them. The results are the same bits either way.
pub const DISABLE_CPU_FEATURES: &str = "GROUNDWORK_DISABLE_CPU_FEATURES";

/// Whether the comma-separated list `value` names AVX-512 (any case, spaces ignored).
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
fn names_avx512(value: &str) -> bool {
    value
        .split(',')
        .any(|f| f.trim().eq_ignore_ascii_case("avx512"))
}

/// Whether the run-time AVX-512 copies may run: the CPU has AVX-512 F, VL, BW and DQ (what
/// they are compiled with) and [`DISABLE_CPU_FEATURES`] does not turn them off. Decided
/// once per process; always false off x86-64.
#[inline]
pub fn avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static AVAILABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
        *AVAILABLE.get_or_init(|| {
            let cpu = std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512vl")
                && std::is_x86_feature_detected!("avx512bw")
                && std::is_x86_feature_detected!("avx512dq");
            let off = std::env::var(DISABLE_CPU_FEATURES).is_ok_and(|v| names_avx512(&v));
            if cpu && off {
                tracing::info!("AVX-512 present but turned off by {DISABLE_CPU_FEATURES}");
            }
            cpu && !off
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether this CPU has every feature the build targets.
#[inline(never)]
pub fn check() -> Result<(), MissingCpuFeatures> {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{__cpuid, __cpuid_count};
        let max_leaf = __cpuid(0).eax;
        let leaf1 = __cpuid(1).ecx;
        let leaf7 = if max_leaf >= 7 {
            __cpuid_count(7, 0).ebx
        } else {
            0
        };
        let ext1 = if __cpuid(0x8000_0000).eax >= 0x8000_0001 {
            __cpuid(0x8000_0001).ecx
        } else {
            0
        };
        // Everything from here to the error message runs on CPUs without AVX and BMI: one
        // feature at a time through an optimisation barrier (left to itself the compiler
        // vectorises the loop with AVX), bits as constant masks (a shift by a variable
        // becomes BMI2's `shlx`). Checked under qemu-user by the CLI's tests.
        let mut missing = [false; 9];
        let mut any = false;
        for (i, (_, f)) in REQUIRED.iter().enumerate() {
            let (reg, bit) = match *f {
                Feature::Leaf1Ecx(b) => (leaf1, b),
                Feature::Leaf7Ebx(b) => (leaf7, b),
                Feature::Ext1Ecx(b) => (ext1, b),
            };
            let m = std::hint::black_box(reg & bit) == 0;
            missing[i] = std::hint::black_box(m);
            any |= m;
        }
        if any {
            return Err(MissingCpuFeatures { missing });
        }
    }
    #[cfg(target_arch = "aarch64")]
    {
        let present = detected();
        let mut missing = [false; 9];
        for (i, (_, compiled)) in REQUIRED.iter().enumerate() {
            missing[i] = *compiled && !present[i];
        }
        if missing.contains(&true) {
            return Err(MissingCpuFeatures { missing });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn this_machine_passes_and_a_missing_feature_is_named() {
        // The tests themselves run x86-64-v3 code: reaching this line means the CPU has it.
        super::check().unwrap();
        let mut missing = [false; 9];
        missing[2] = true;
        missing[8] = true;
        let m = super::MissingCpuFeatures { missing };
        let s = m.to_string();
        #[cfg(target_arch = "x86_64")]
        assert!(
            s.contains("lacks avx2 lzcnt,") && s.contains("x86-64-v3"),
            "{s}"
        );
        #[cfg(target_arch = "aarch64")]
        assert!(
            s.contains("lacks rcpc sve,") && s.contains("Armv8-A"),
            "{s}"
        );
        assert!(s.contains("target-cpu=native"), "{s}");
    }

    #[test]
    fn the_switch_names_avx512_in_a_list() {
        for on in ["avx512", "AVX512", " avx512 ", "sse4,avx512", "avx512,"] {
            assert!(super::names_avx512(on), "{on:?}");
        }
        for off in ["", "avx2", "avx5120", "avx512f", "noavx512"] {
            assert!(!super::names_avx512(off), "{off:?}");
        }
    }
}
