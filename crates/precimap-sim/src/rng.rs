//! Small, self-contained random numbers, so that a seed gives the same campaign with any version
//! of any crate: splitmix64 (seeding and stateless hashing) and xoshiro256++ (sequential streams).
//!
//! Two styles are used on purpose:
//! - sequential [`Rng`] streams for things generated once in a fixed order (the town, a pass's
//!   speeds and error processes);
//! - stateless hashes of a key ([`unit`], [`normal`]) for per-measurement randomness (range noise,
//!   foliage depth, intensity), so a ray's outcome does not depend on how often or in which order
//!   primitives are tested, nor on which thread simulates which strip.

/// One splitmix64 step.
#[inline]
pub fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Stateless 64-bit mix of one value (the splitmix64 finaliser).
#[inline]
pub fn mix(x: u64) -> u64 {
    let mut s = x;
    splitmix64(&mut s)
}

/// Hash of two values; order matters.
#[inline]
pub fn hash2(a: u64, b: u64) -> u64 {
    mix(a.wrapping_mul(0xD6E8_FEB8_6659_FD93) ^ mix(b))
}

/// Hash of three values.
#[inline]
pub fn hash3(a: u64, b: u64, c: u64) -> u64 {
    hash2(hash2(a, b), c)
}

/// Uniform in the open interval (0, 1) from a key.
#[inline]
pub fn unit(key: u64) -> f64 {
    ((mix(key) >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64)
}

/// Standard normal from a key (Box–Muller on two derived uniforms).
#[inline]
pub fn normal(key: u64) -> f64 {
    let u1 = unit(key);
    let u2 = unit(key ^ 0x5851_F42D_4C95_7F2D);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Uniformly distributed unit vector from a key.
pub fn unit_vector(key: u64) -> [f64; 3] {
    let z = 2.0 * unit(key) - 1.0;
    let a = std::f64::consts::TAU * unit(key ^ 0x2545_F491_4F6C_DD1D);
    let s = (1.0 - z * z).max(0.0).sqrt();
    [s * a.cos(), s * a.sin(), z]
}

/// xoshiro256++ (Blackman & Vigna), seeded through splitmix64.
#[derive(Clone, Debug)]
pub struct Rng {
    s: [u64; 4],
}

impl Rng {
    /// An independent stream for `(seed, stream)`.
    pub fn new(seed: u64, stream: u64) -> Self {
        let mut sm = hash2(seed, stream);
        let s = [splitmix64(&mut sm), splitmix64(&mut sm), splitmix64(&mut sm), splitmix64(&mut sm)];
        Self { s }
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    #[inline]
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f64()
    }

    /// Uniform in the closed range of a `[lo, hi]` config pair.
    #[inline]
    pub fn within(&mut self, r: [f64; 2]) -> f64 {
        self.range(r[0], r[1])
    }

    /// True with probability `p`.
    #[inline]
    pub fn chance(&mut self, p: f64) -> bool {
        self.f64() < p
    }

    /// Standard normal.
    pub fn normal(&mut self) -> f64 {
        normal(self.next_u64())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xoshiro_reference_values() {
        // xoshiro256++ from state {1, 2, 3, 4}, worked by hand: rotl(5, 23) + 1, then rotl(7 + 6·2⁴⁵, 23) + 7.
        let mut r = Rng { s: [1, 2, 3, 4] };
        assert_eq!(r.next_u64(), 41_943_041);
        assert_eq!(r.next_u64(), 58_720_359);
    }

    #[test]
    fn streams_are_deterministic_and_distinct() {
        let a: Vec<u64> = (0..4)
            .map({
                let mut r = Rng::new(7, 1);
                move |_| r.next_u64()
            })
            .collect();
        let mut r = Rng::new(7, 1);
        assert!(a.iter().all(|&v| v == r.next_u64()));
        let mut other = Rng::new(7, 2);
        assert_ne!(a[0], other.next_u64());
    }

    #[test]
    fn moments() {
        let n = 200_000u64;
        let (mut s1, mut s2, mut su) = (0.0, 0.0, 0.0);
        for k in 0..n {
            let x = normal(hash2(99, k));
            s1 += x;
            s2 += x * x;
            su += unit(hash2(98, k));
        }
        let n = n as f64;
        assert!((s1 / n).abs() < 0.01, "mean {}", s1 / n);
        assert!((s2 / n - 1.0).abs() < 0.02, "var {}", s2 / n);
        assert!((su / n - 0.5).abs() < 0.005);
        let v = unit_vector(5);
        assert!((v[0] * v[0] + v[1] * v[1] + v[2] * v[2] - 1.0).abs() < 1e-12);
    }
}
