//! The workspace's one source of deterministic random numbers: a SplitMix64 stream (scenes and
//! noise in `record`, initial weights here, training crops in `replay`), and a counter-based hash
//! for per-pixel noise (independent of thread scheduling).

/// SplitMix64 (Steele, Lea, Flood 2014): tiny, fast, and good enough for procedural content.
#[derive(Debug, Clone)]
pub struct SplitMix64 {
    state: u64,
}

impl SplitMix64 {
    /// A stream from a seed.
    pub fn new(seed: u64) -> Self {
        Self { state: seed }
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.state)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        unit_from_bits(self.next_u64())
    }

    /// Uniform `f32` in [lo, hi), from the top 24 bits (what the networks' initial weights use).
    pub fn uniform_f32(&mut self, lo: f32, hi: f32) -> f32 {
        let unit = (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        lo + (hi - lo) * unit
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in [0, n).
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 { 0 } else { self.next_u64() % n }
    }

    /// Uniform integer in [lo, hi).
    pub fn range_usize(&mut self, lo: usize, hi: usize) -> usize {
        lo + self.below((hi.saturating_sub(lo)) as u64) as usize
    }

    /// Standard normal (Box–Muller).
    pub fn gaussian(&mut self) -> f64 {
        let (a, b) = (self.next_u64(), self.next_u64());
        gaussian_from_bits(a, b)
    }
}

/// The SplitMix64 output function: a strong 64-bit mixer.
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Hash of a seed and three counters.
pub fn hash4(seed: u64, a: u64, b: u64, c: u64) -> u64 {
    mix64(mix64(mix64(seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15)) ^ b) ^ c.wrapping_mul(0xD6E8_FEB8_6659_FD93))
}

/// Uniform in [0, 1) from 64 bits.
pub fn unit_from_bits(bits: u64) -> f64 {
    (bits >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Standard normal from 128 bits (Box–Muller).
pub fn gaussian_from_bits(a: u64, b: u64) -> f64 {
    let u1 = unit_from_bits(a).max(1e-300);
    let u2 = unit_from_bits(b);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}
