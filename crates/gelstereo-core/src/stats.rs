//! Small statistics shared by the localization and tracking crates.

/// The median of `values` (which may be reordered): the middle value, or the mean of the two middle
/// ones for an even count, in `f64::total_cmp` order, so equal to the median of a full sort bit for
/// bit; `None` when empty. Picked by selection, not a full sort (up to 16 values: a sort of integer
/// keys on the stack): the per-marker medians of the post-processing and the tracker run on every
/// frame.
pub fn median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    if n <= SMALL {
        return Some(small_median(values));
    }
    let (below, &mut middle, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        return Some(middle);
    }
    let below_middle = below.iter().copied().max_by(f64::total_cmp)?;
    Some(0.5 * (below_middle + middle))
}

/// Lists up to this long take [`small_median`]: a tracker takes thousands of medians of a marker's
/// 8 neighbours per frame.
const SMALL: usize = 16;

/// `f64::total_cmp`'s order as an integer's: a value's bits with those below the sign flipped when
/// it is set. Its own inverse.
fn total_order_key(v: f64) -> i64 {
    let bits = v.to_bits() as i64;
    bits ^ ((((bits >> 63) as u64) >> 1) as i64)
}

/// [`median`] of 1 to [`SMALL`] values (the same bits): the values' integer keys sorted on the
/// stack, a few times faster on such lists than selection through a comparison function.
fn small_median(values: &[f64]) -> f64 {
    let n = values.len();
    let mut keys = [0i64; SMALL];
    for (k, v) in keys.iter_mut().zip(values) {
        *k = total_order_key(*v);
    }
    let keys = &mut keys[..n];
    keys.sort_unstable();
    let value = |k: i64| f64::from_bits(total_order_key(f64::from_bits(k as u64)) as u64);
    let middle = value(keys[n / 2]);
    if n % 2 == 1 {
        middle
    } else {
        0.5 * (value(keys[n / 2 - 1]) + middle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Selection gives the median a full sort gives, bit for bit (odd and even counts, repeated
    /// values, both zeros).
    #[test]
    fn median_by_selection_is_the_sorted_median() {
        let mut state = 11u64;
        for n in 1..60usize {
            let values: Vec<f64> = (0..n)
                .map(|k| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    match k % 7 {
                        0 => -0.0,
                        1 => 0.0,
                        2 => 3.5,
                        _ => (state >> 11) as f64 / (1u64 << 53) as f64 * 20.0 - 5.0,
                    }
                })
                .collect();
            let mut sorted = values.clone();
            sorted.sort_by(f64::total_cmp);
            let want = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            let got = median(&mut values.clone()).map(f64::to_bits);
            assert_eq!(got, Some(want.to_bits()), "{n} values");
        }
        assert_eq!(median(&mut []), None);
    }
}
