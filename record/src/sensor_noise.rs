//! The renderer's sensor noise: a standard normal per pixel and channel from hashed bits, by
//! Box–Muller, as [`fuse::rng::gaussian_from_bits`] but with the logarithm and the cosine inlined
//! (fdlibm's kernels, within an ulp or two of the system's) and without branches, so that a
//! row's draws run four to a vector instead of each paying two library calls. The image rounds
//! the noise to 8-bit levels; the draws agree with the library's to about 1e-15 (tests below),
//! far below what the rounding can see.

// fdlibm's constants as published (their last digits round to the same doubles).
#![allow(clippy::excessive_precision)]

/// Standard normal from 128 bits (Box–Muller), as [`fuse::rng::gaussian_from_bits`].
#[inline]
pub(crate) fn gaussian_from_bits(a: u64, b: u64) -> f64 {
    let u1 = fuse::rng::unit_from_bits(a).max(1e-300);
    let u2 = fuse::rng::unit_from_bits(b);
    (-2.0 * ln(u1)).sqrt() * cos_turns(u2)
}

/// [`gaussian_from_bits`] of each pair `(a[i], b[i])` into `out[i]`: the same numbers. Each draw
/// is a long chain of dependent arithmetic; a loop of nothing else, without branches, runs four
/// draws to a vector and overlaps the rest.
pub(crate) fn gaussians_from_bits(a: &[u64], b: &[u64], out: &mut [f64]) {
    for ((out, &a), &b) in out.iter_mut().zip(a).zip(b) {
        *out = gaussian_from_bits(a, b);
    }
}

/// Natural logarithm of a positive normal `x` (fdlibm's `__ieee754_log`, both of its ways of
/// summing computed and one chosen, so that a loop of these has no branch).
#[inline]
fn ln(x: f64) -> f64 {
    const LN2_HI: f64 = 6.931_471_803_691_238_164_90e-01;
    const LN2_LO: f64 = 1.908_214_929_270_587_700_02e-10;
    const LG1: f64 = 6.666_666_666_666_735_130e-01;
    const LG2: f64 = 3.999_999_999_940_941_908e-01;
    const LG3: f64 = 2.857_142_874_366_239_149e-01;
    const LG4: f64 = 2.222_219_843_214_978_396e-01;
    const LG5: f64 = 1.818_357_216_161_805_012e-01;
    const LG6: f64 = 1.531_383_769_920_937_332e-01;
    const LG7: f64 = 1.479_819_860_511_658_591e-01;
    let bits = x.to_bits();
    let high = (bits >> 32) as i64;
    let hx = high & 0x000f_ffff;
    // x = 2^k (1 + f) with 1 + f in [sqrt(2)/2, sqrt(2)).
    let i = (hx + 0x95f64) & 0x10_0000;
    let normalised = f64::from_bits((((hx | (i ^ 0x3ff0_0000)) as u64) << 32) | (bits & 0xffff_ffff));
    let k = (high >> 20) - 1023 + (i >> 20);
    let f = normalised - 1.0;
    let dk = k as f64;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG2 + w * (LG4 + w * LG6));
    let t2 = z * (LG1 + w * (LG3 + w * (LG5 + w * LG7)));
    let r = t2 + t1;
    let hfsq = 0.5 * f * f;
    let far = dk * LN2_HI - ((hfsq - (s * (hfsq + r) + dk * LN2_LO)) - f);
    let near = dk * LN2_HI - ((s * (f - r) - dk * LN2_LO) - f);
    if ((hx - 0x6147a) | (0x6b851 - hx)) > 0 {
        far
    } else {
        near
    }
}

/// `cos(2π t)` for `t` in [0, 1): the nearest quarter turn taken out exactly, then fdlibm's
/// kernels on [−π/4, π/4].
#[inline]
fn cos_turns(t: f64) -> f64 {
    let quarter = (t * 4.0).round();
    // Exact: t and quarter / 4 are multiples of 2^-53 below 1.
    let x = std::f64::consts::TAU * (t - quarter * 0.25);
    let q = quarter as i64 & 3;
    let (sin, cos) = (kernel_sin(x), kernel_cos(x));
    let value = if q & 1 == 0 { cos } else { sin };
    // cos(x), −sin(x), −cos(x), sin(x) for quarters 0 to 3.
    if q == 1 || q == 2 { -value } else { value }
}

/// sin on [−π/4, π/4] (fdlibm's `__kernel_sin`).
#[inline]
fn kernel_sin(x: f64) -> f64 {
    const S1: f64 = -1.666_666_666_666_663_243_48e-01;
    const S2: f64 = 8.333_333_333_322_489_461_24e-03;
    const S3: f64 = -1.984_126_982_985_794_931_34e-04;
    const S4: f64 = 2.755_731_370_707_006_767_89e-06;
    const S5: f64 = -2.505_076_025_340_686_341_95e-08;
    const S6: f64 = 1.589_690_995_211_550_102_21e-10;
    let z = x * x;
    let v = z * x;
    let r = S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)));
    x + v * (S1 + z * r)
}

/// cos on [−π/4, π/4] (fdlibm's `__kernel_cos`, both of its ways of summing computed).
#[inline]
fn kernel_cos(x: f64) -> f64 {
    const C1: f64 = 4.166_666_666_666_660_190_37e-02;
    const C2: f64 = -1.388_888_888_887_410_957_49e-03;
    const C3: f64 = 2.480_158_728_947_672_941_78e-05;
    const C4: f64 = -2.755_731_435_139_066_330_35e-07;
    const C5: f64 = 2.087_572_321_298_174_827_90e-09;
    const C6: f64 = -1.135_964_755_778_819_482_65e-11;
    let z = x * x;
    let r = z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))));
    let small = 1.0 - (0.5 * z - z * r);
    // Above 0.3: x / 4 with its low word cleared, so that 1 − qx is exact (|x| ≤ π/4).
    let qx = f64::from_bits((x.abs() * 0.25).to_bits() & 0xffff_ffff_0000_0000);
    let large = (1.0 - qx) - ((0.5 * z - qx) - z * r);
    if x.abs() < 0.3 { small } else { large }
}

#[cfg(test)]
mod tests {
    use super::*;
    use fuse::rng::{mix64, unit_from_bits};

    /// The library's Box–Muller, term by term, against these kernels over a million hashed draws
    /// and the ends of their ranges.
    #[test]
    fn draws_agree_with_the_library_to_an_ulp_or_two() {
        let (mut worst_ln, mut worst_cos, mut worst_draw) = (0f64, 0f64, 0f64);
        let ends = [
            0.0,
            1e-300,
            f64::EPSILON,
            0.125,
            0.25,
            0.375,
            0.5,
            0.625,
            0.75,
            0.875,
            1.0 - f64::EPSILON / 2.0,
        ];
        let draws = (0..1_000_000u64).map(|i| (mix64(i), mix64(i ^ 0x5851_F42D)));
        for (a, b) in draws {
            let (u1, u2) = (unit_from_bits(a).max(1e-300), unit_from_bits(b));
            worst_ln = worst_ln.max((ln(u1) - u1.ln()).abs() / u1.ln().abs().max(f64::MIN_POSITIVE));
            worst_cos = worst_cos.max((cos_turns(u2) - (std::f64::consts::TAU * u2).cos()).abs());
            worst_draw = worst_draw.max((gaussian_from_bits(a, b) - fuse::rng::gaussian_from_bits(a, b)).abs());
        }
        for &u in &ends {
            let u1 = f64::max(u, 1e-300);
            if u1 != 1.0 {
                worst_ln = worst_ln.max((ln(u1) - u1.ln()).abs() / u1.ln().abs());
            }
            worst_cos = worst_cos.max((cos_turns(u) - (std::f64::consts::TAU * u).cos()).abs());
        }
        // Relative to the logarithm; absolute for the cosine (the library's argument 2πt is
        // itself rounded, by up to 4.4e-16) and for the draw (at most about 8.5 in size).
        assert!(worst_ln <= 2.5e-16, "ln differs by {worst_ln:e} (relative)");
        assert!(worst_cos <= 1.2e-15, "cos differs by {worst_cos:e}");
        assert!(worst_draw <= 1e-14, "draws differ by {worst_draw:e}");
        assert!((ln(std::f64::consts::E) - 1.0).abs() <= f64::EPSILON);
        assert!((ln(0.5) + std::f64::consts::LN_2).abs() <= f64::EPSILON);
    }

    #[test]
    fn a_row_of_draws_is_the_draws_one_by_one() {
        let a: Vec<u64> = (0..1001u64).map(mix64).collect();
        let b: Vec<u64> = a.iter().map(|&x| mix64(x ^ 0x5851_F42D)).collect();
        let mut row = vec![0.0; a.len()];
        gaussians_from_bits(&a, &b, &mut row);
        for ((&x, &a), &b) in row.iter().zip(&a).zip(&b) {
            assert_eq!(x.to_bits(), gaussian_from_bits(a, b).to_bits());
        }
    }
}
