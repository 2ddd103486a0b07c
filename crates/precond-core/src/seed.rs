//! Seeds derived from seeds: the one place where the service and the harness hash a seed with
//! what a random choice depends on (a fit's version, a planning problem, a purpose and an index).
//!
//! Every function is a bijective-ish 64-bit mix built on SplitMix64's finaliser (Steele, Lea and
//! Flood 2014), so nearby inputs give unrelated outputs and the same inputs always give the same
//! seed, on every platform.

/// SplitMix64's increment, the golden ratio in 64-bit fixed point.
const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64's output finaliser.
fn finalize(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// One SplitMix64 step from state `z`: `finalize(z + golden)`.
pub fn splitmix64(z: u64) -> u64 {
    finalize(z.wrapping_add(GOLDEN))
}

/// The seed of `salt` under `seed` (e.g. fit `version` of an experiment seeded `seed`).
pub fn mix(seed: u64, salt: i64) -> u64 {
    finalize(seed ^ (salt as u64).wrapping_mul(GOLDEN))
}

/// The seed of a sequence of numbers under `seed` and `salt` (e.g. a planning problem's start
/// and goal, under the experiment's seed and how much data it has seen). Every bit of every
/// number counts: `0.0` and `-0.0` give different seeds.
pub fn mix_values(seed: u64, salt: i64, values: impl IntoIterator<Item = f64>) -> u64 {
    values
        .into_iter()
        .fold(mix(seed, salt), |h, x| mix(h ^ x.to_bits(), 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix64_matches_the_reference_sequence() {
        // The first outputs of the reference SplitMix64 generator seeded with 0.
        let mut state = 0u64;
        let mut next = || {
            let out = splitmix64(state);
            state = state.wrapping_add(GOLDEN);
            out
        };
        assert_eq!(next(), 0xE220_A839_7B1D_CDAF);
        assert_eq!(next(), 0x6E78_9E6A_A1B9_65F4);
    }

    #[test]
    fn seeds_depend_on_every_input() {
        assert_ne!(mix(1, 2), mix(1, 3));
        assert_ne!(mix(1, 2), mix(2, 2));
        assert_eq!(mix_values(7, 1, [1.0, 2.0]), mix_values(7, 1, [1.0, 2.0]));
        assert_ne!(mix_values(7, 1, [1.0, 2.0]), mix_values(7, 1, [2.0, 1.0]));
        assert_ne!(mix_values(7, 1, [0.0]), mix_values(7, 1, [-0.0]));
    }
}
