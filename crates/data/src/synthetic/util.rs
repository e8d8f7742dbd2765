//! Deterministic hashing and value noise used for procedural textures and porous shapes.

/// SplitMix64 finaliser: a well-mixed 64-bit hash of `z`.
#[inline]
pub(crate) fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Hash of a seed and three signed integers.
#[inline]
pub(crate) fn hash3(seed: u64, a: i64, b: i64, c: i64) -> u64 {
    let mut h = mix64(seed ^ 0x9e37_79b9_7f4a_7c15);
    h = mix64(h ^ (a as u64));
    h = mix64(h ^ (b as u64).wrapping_mul(0x2545_f491_4f6c_dd1d));
    mix64(h ^ (c as u64).wrapping_mul(0x8cb9_2ba7_2f3d_8dd7))
}

/// Map a hash to `[0, 1)`.
#[inline]
pub(crate) fn unit(h: u64) -> f64 {
    (h >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Smooth 2D value noise in `[0, 1)`: bilinear (smoothstep) interpolation of lattice hashes at
/// integer points of `(x, y)`.
pub(crate) fn value_noise2(seed: u64, x: f64, y: f64) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (i, j) = (x0 as i64, y0 as i64);
    let v = |a: i64, b: i64| unit(hash3(seed, a, b, 0x51));
    let top = v(i, j) * (1.0 - sx) + v(i + 1, j) * sx;
    let bot = v(i, j + 1) * (1.0 - sx) + v(i + 1, j + 1) * sx;
    top * (1.0 - sy) + bot * sy
}

/// A seed derived from a base seed and a text label (FNV-1a of the label, then mixed).
pub(crate) fn derive_seed(seed: u64, label: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in label.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    mix64(seed ^ mix64(h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_is_in_range_and_roughly_uniform() {
        let n = 10_000;
        let mut sum = 0.0;
        for i in 0..n {
            let u = unit(hash3(7, i, -i, 3));
            assert!((0.0..1.0).contains(&u));
            sum += u;
        }
        let mean = sum / n as f64;
        assert!((mean - 0.5).abs() < 0.02, "mean {mean}");
    }

    #[test]
    fn value_noise_is_continuous_and_bounded() {
        for i in 0..200 {
            let x = i as f64 * 0.37 - 20.0;
            let a = value_noise2(3, x, 1.3);
            let b = value_noise2(3, x + 1e-6, 1.3);
            assert!((0.0..1.0).contains(&a));
            assert!((a - b).abs() < 1e-4);
        }
        assert_ne!(derive_seed(1, "00"), derive_seed(1, "08"));
        assert_ne!(derive_seed(1, "00"), derive_seed(2, "00"));
    }
}
