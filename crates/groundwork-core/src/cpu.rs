//! The CPU features the build relies on, checked when a binary starts.
//!
//! Release builds target x86-64-v3 (`.cargo/config.toml`): the compiler may use AVX2, FMA,
//! BMI1/2, F16C, LZCNT and MOVBE anywhere, so on an older CPU the first such instruction
//! kills the process with SIGILL and no message. Binaries call [`check`] first thing and
//! exit with a clear error instead. The check itself uses only `cpuid` and integer tests, so
//! it runs on any x86-64 CPU.

/// The features the compiler was told it may use, by name, with how to test for them.
#[cfg(target_arch = "x86_64")]
const REQUIRED: [(&str, Feature); 9] = [
    ("avx", Feature::Leaf1Ecx(28)),
    // The OS must save the AVX registers on context switches (XSAVE enabled by the OS).
    ("osxsave", Feature::Leaf1Ecx(27)),
    ("avx2", Feature::Leaf7Ebx(5)),
    ("fma", Feature::Leaf1Ecx(12)),
    ("bmi1", Feature::Leaf7Ebx(3)),
    ("bmi2", Feature::Leaf7Ebx(8)),
    ("f16c", Feature::Leaf1Ecx(29)),
    ("movbe", Feature::Leaf1Ecx(22)),
    ("lzcnt", Feature::Ext1Ecx(5)),
];

#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
enum Feature {
    Leaf1Ecx(u32),
    Leaf7Ebx(u32),
    Ext1Ecx(u32),
}

/// The CPU lacks features this build was compiled to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MissingCpuFeatures {
    /// Bit i set: the i-th required feature is missing.
    mask: u32,
}

impl MissingCpuFeatures {
    /// Names of the missing features.
    pub fn names(&self) -> impl Iterator<Item = &'static str> + '_ {
        #[cfg(target_arch = "x86_64")]
        let names = REQUIRED.iter().map(|(n, _)| *n);
        #[cfg(not(target_arch = "x86_64"))]
        let names = std::iter::empty();
        names
            .enumerate()
            .filter(|(i, _)| self.mask & (1 << i) != 0)
            .map(|(_, n)| n)
    }
}

impl std::fmt::Display for MissingCpuFeatures {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("this CPU lacks")?;
        for n in self.names() {
            f.write_str(" ")?;
            f.write_str(n)?;
        }
        f.write_str(
            ", which this build uses (it targets x86-64-v3: Intel Haswell, AMD Zen 1 or later). \
             Build for this CPU: RUSTFLAGS='-C target-cpu=native' cargo build --release",
        )
    }
}

impl std::error::Error for MissingCpuFeatures {}

/// Whether this CPU has every feature the build targets.
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
        let mut mask = 0;
        for (i, (_, f)) in REQUIRED.iter().enumerate() {
            let (reg, bit) = match *f {
                Feature::Leaf1Ecx(b) => (leaf1, b),
                Feature::Leaf7Ebx(b) => (leaf7, b),
                Feature::Ext1Ecx(b) => (ext1, b),
            };
            if reg & (1 << bit) == 0 {
                mask |= 1 << i;
            }
        }
        if mask != 0 {
            return Err(MissingCpuFeatures { mask });
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
        let m = super::MissingCpuFeatures {
            mask: 0b100 | 1 << 8,
        };
        let s = m.to_string();
        #[cfg(target_arch = "x86_64")]
        assert!(
            s.contains("lacks avx2 lzcnt,") && s.contains("x86-64-v3"),
            "{s}"
        );
        assert!(s.contains("target-cpu=native"), "{s}");
    }
}
