//! The mutations: byte-level (bit flips, interesting bytes and integers,
//! insertions, deletions, duplications, truncation, splicing two seeds)
//! and, for text inputs, token-level (numbers replaced by extreme ones,
//! JSON delimiters dropped or repeated).

use rand::{Rng, RngExt};

const INTERESTING_BYTES: [u8; 8] = [0, 1, 0x7f, 0x80, 0xfe, 0xff, b'{', b'"'];
const INTERESTING_INTS: [i64; 10] = [
    0,
    -1,
    1,
    255,
    65_535,
    i32::MAX as i64,
    i32::MIN as i64,
    u32::MAX as i64,
    i64::MAX,
    1 << 40,
];
const EXTREME_NUMBERS: [&str; 12] = [
    "0",
    "-1",
    "1e308",
    "-1e308",
    "1e-320",
    "NaN",
    "Infinity",
    "99999999999",
    "4294967296",
    "18446744073709551616",
    "0.0",
    "-0",
];

/// A mutant of one of `seeds` (1 to 8 mutations).
pub fn mutant(seeds: &[Vec<u8>], text: bool, rng: &mut impl Rng) -> Vec<u8> {
    let mut data = seeds[rng.random_range(0..seeds.len())].clone();
    let count = 1 + rng.random_range(0..8);
    for _ in 0..count {
        if text && rng.random_bool(0.5) {
            mutate_text(&mut data, rng);
        } else {
            mutate_bytes(&mut data, seeds, rng);
        }
    }
    data
}

fn mutate_bytes(data: &mut Vec<u8>, seeds: &[Vec<u8>], rng: &mut impl Rng) {
    let len = data.len();
    let choice = rng.random_range(0..9);
    match choice {
        0 if len > 0 => {
            let i = rng.random_range(0..len);
            data[i] ^= 1 << rng.random_range(0..8);
        }
        1 if len > 0 => {
            let i = rng.random_range(0..len);
            data[i] = INTERESTING_BYTES[rng.random_range(0..INTERESTING_BYTES.len())];
        }
        2 if len >= 8 => {
            let i = rng.random_range(0..len - 7);
            let value = INTERESTING_INTS[rng.random_range(0..INTERESTING_INTS.len())];
            let width = [1usize, 2, 4, 8][rng.random_range(0..4)];
            let bytes = value.to_le_bytes();
            data[i..i + width].copy_from_slice(&bytes[..width]);
        }
        3 => {
            let i = if len == 0 {
                0
            } else {
                rng.random_range(0..=len)
            };
            let n = 1 + rng.random_range(0..16);
            let fill: Vec<u8> = (0..n).map(|_| rng.random()).collect();
            data.splice(i..i, fill);
        }
        4 if len > 0 => {
            let i = rng.random_range(0..len);
            let n = 1 + rng.random_range(0..(len - i).min(64));
            data.drain(i..i + n);
        }
        5 if len > 0 => {
            let i = rng.random_range(0..len);
            let n = 1 + rng.random_range(0..(len - i).min(64));
            let copy = data[i..i + n].to_vec();
            let j = rng.random_range(0..=len);
            data.splice(j..j, copy);
        }
        6 if len > 0 => data.truncate(rng.random_range(0..len)),
        7 => {
            // Splice: this input's head, another seed's tail.
            let other = &seeds[rng.random_range(0..seeds.len())];
            if !other.is_empty() {
                let cut = if len == 0 {
                    0
                } else {
                    rng.random_range(0..len)
                };
                let from = rng.random_range(0..other.len());
                data.truncate(cut);
                data.extend_from_slice(&other[from..]);
            }
        }
        _ => {
            // A long run of one byte (sizes, counts, nesting).
            let i = if len == 0 {
                0
            } else {
                rng.random_range(0..=len)
            };
            let byte = INTERESTING_BYTES[rng.random_range(0..INTERESTING_BYTES.len())];
            let n = 1 + rng.random_range(0..4096);
            data.splice(i..i, std::iter::repeat_n(byte, n));
        }
    }
}

/// Replaces a number token by an extreme one, or drops or repeats a JSON
/// delimiter.
fn mutate_text(data: &mut Vec<u8>, rng: &mut impl Rng) {
    let numbers: Vec<(usize, usize)> = number_tokens(data);
    if !numbers.is_empty() && rng.random_bool(0.7) {
        let (start, end) = numbers[rng.random_range(0..numbers.len())];
        let replacement = EXTREME_NUMBERS[rng.random_range(0..EXTREME_NUMBERS.len())];
        data.splice(start..end, replacement.bytes());
        return;
    }
    let delimiters: Vec<usize> = data
        .iter()
        .enumerate()
        .filter(|(_, b)| matches!(b, b'{' | b'}' | b'[' | b']' | b',' | b':' | b'"'))
        .map(|(i, _)| i)
        .collect();
    if delimiters.is_empty() {
        return;
    }
    let i = delimiters[rng.random_range(0..delimiters.len())];
    if rng.random_bool(0.5) {
        data.remove(i);
    } else {
        let byte = data[i];
        data.splice(i..i, std::iter::repeat_n(byte, 1 + rng.random_range(0..64)));
    }
}

/// Byte ranges of decimal number tokens.
fn number_tokens(data: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < data.len() {
        let starts = data[i].is_ascii_digit()
            || (data[i] == b'-' && data.get(i + 1).is_some_and(u8::is_ascii_digit));
        if starts {
            let start = i;
            i += 1;
            while i < data.len()
                && (data[i].is_ascii_digit() || matches!(data[i], b'.' | b'e' | b'E' | b'-' | b'+'))
            {
                i += 1;
            }
            out.push((start, i));
        } else {
            i += 1;
        }
    }
    out
}
