//! A seeded byte mutator: every input is a pure function of `(seed, target, iteration)`, so a
//! finding is reproduced from its file name alone.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Largest input the mutator produces, bytes (longer results are truncated).
pub const MAX_INPUT_BYTES: usize = 8 << 20;

/// Integers that often sit at the edges of parsers' checks.
const INTERESTING: [u64; 22] = [
    0,
    1,
    2,
    3,
    7,
    8,
    14,
    16,
    0x7f,
    0x80,
    0xff,
    0x100,
    0x7fff,
    0x8000,
    0xffff,
    0x1_0000,
    100_000,
    0x7fff_ffff,
    0x8000_0000,
    0xffff_ffff,
    0x7fff_ffff_ffff_ffff,
    u64::MAX,
];

/// Decimal (and not quite decimal) strings for the numeric fields of text headers: npy shapes,
/// PFM sizes and scales, JSON numbers.
const INTERESTING_TEXT: [&str; 22] = [
    "0",
    "1",
    "-1",
    "2",
    "14",
    "65535",
    "65536",
    "100000",
    "4294967296",
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999999",
    "1e309",
    "-1e309",
    "NaN",
    "inf",
    "-0",
    "0.5",
    "1e-45",
    "",
    "null",
    "[]",
];

/// Mutates `inputs[pick]`-style seeds into new inputs.
pub struct Mutator {
    rng: ChaCha8Rng,
}

impl Mutator {
    /// The mutator of one input: `seed`, target index and iteration mixed into one ChaCha8 seed.
    pub fn for_input(seed: u64, target: u64, iteration: u64) -> Self {
        let mixed = seed
            ^ target.wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ iteration
                .wrapping_mul(0xD1B5_4A32_D192_ED03)
                .rotate_left(17);
        Self {
            rng: ChaCha8Rng::seed_from_u64(mixed),
        }
    }

    /// A uniform index below `n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        self.rng.random_range(0..n)
    }

    /// `true` with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.rng.random_bool(p)
    }

    /// Applies 1 to 6 stacked mutations to `data`; `others` are the other seeds (for splicing).
    pub fn mutate(&mut self, data: &mut Vec<u8>, others: &[&[u8]]) {
        let rounds = 1 + self.below(6);
        for _ in 0..rounds {
            self.mutate_once(data, others);
        }
        data.truncate(MAX_INPUT_BYTES);
    }

    /// A position biased to the start of the data, where the headers are (half the time within
    /// the first 64 bytes).
    fn position(&mut self, len: usize) -> usize {
        if len == 0 {
            return 0;
        }
        if self.chance(0.5) {
            self.below(len.min(64))
        } else {
            self.below(len)
        }
    }

    fn mutate_once(&mut self, data: &mut Vec<u8>, others: &[&[u8]]) {
        let len = data.len();
        match self.below(10) {
            // Bit flip.
            0 if len > 0 => {
                let i = self.position(len);
                data[i] ^= 1 << self.below(8);
            }
            // Set a byte.
            1 if len > 0 => {
                let i = self.position(len);
                data[i] = self.rng.random();
            }
            // Insert random bytes.
            2 => {
                let i = self.position(len + 1).min(len);
                let n = 1 + self.below(16);
                let bytes: Vec<u8> = (0..n).map(|_| self.rng.random()).collect();
                data.splice(i..i, bytes);
            }
            // Delete a range.
            3 if len > 0 => {
                let i = self.position(len);
                let n = 1 + self.below((len - i).min(64));
                data.drain(i..i + n);
            }
            // Splice: a range of another seed overwrites or is inserted.
            4 if !others.is_empty() => {
                let other = others[self.below(others.len())];
                if other.is_empty() {
                    return;
                }
                let a = self.below(other.len());
                let n = 1 + self.below((other.len() - a).min(256));
                let piece = other[a..a + n].to_vec();
                let i = self.position(len + 1).min(len);
                if self.chance(0.5) {
                    data.splice(i..i, piece);
                } else {
                    let end = (i + n).min(len);
                    data.splice(i..end, piece);
                }
            }
            // An interesting integer, 1/2/4/8 bytes, either byte order.
            5 | 6 if len > 0 => {
                let width = [1usize, 2, 4, 8][self.below(4)];
                let v = INTERESTING[self.below(INTERESTING.len())];
                let v = if self.chance(0.2) {
                    v.wrapping_neg()
                } else {
                    v
                };
                let bytes = if self.chance(0.5) {
                    v.to_le_bytes()[..width].to_vec()
                } else {
                    v.to_be_bytes()[8 - width..].to_vec()
                };
                let i = self.position(len);
                let end = (i + width).min(len);
                data.splice(i..end, bytes);
            }
            // Header field: replace a run of ASCII digits (a size, a shape, a number) by an
            // interesting decimal string.
            7 | 8 => {
                let runs = digit_runs(data);
                if runs.is_empty() {
                    return;
                }
                let (a, b) = runs[self.below(runs.len())];
                let text = INTERESTING_TEXT[self.below(INTERESTING_TEXT.len())];
                data.splice(a..b, text.bytes());
            }
            // Truncate.
            _ if len > 1 => {
                let n = self.below(len);
                data.truncate(n);
            }
            _ => {}
        }
    }
}

/// Numbers for [`Mutator::mutate_json`]: the edges of every check a JSON field meets (signs,
/// zero, subnormals, overflow to f32 infinity, integers past 2^53 and u64, fractions where
/// integers are expected).
const INTERESTING_JSON_NUMBERS: [&str; 18] = [
    "0",
    "-0.0",
    "1",
    "-1",
    "0.5",
    "2",
    "1e-45",
    "-1e-45",
    "1e-320",
    "3.5e38",
    "1e308",
    "-1e308",
    "9007199254740993",
    "4294967296",
    "18446744073709551615",
    "12297829382473034411",
    "65535",
    "100000000",
];

/// A path to a node of a JSON document: object keys and array indices from the root.
#[derive(Debug, Clone)]
enum Step {
    Key(String),
    Index(usize),
}

/// Every node of `v` (the root included), in document order, as paths from the root.
fn json_paths(v: &serde_json::Value, prefix: &mut Vec<Step>, out: &mut Vec<Vec<Step>>) {
    out.push(prefix.clone());
    match v {
        serde_json::Value::Object(m) => {
            for (k, child) in m {
                prefix.push(Step::Key(k.clone()));
                json_paths(child, prefix, out);
                prefix.pop();
            }
        }
        serde_json::Value::Array(a) => {
            for (i, child) in a.iter().enumerate() {
                prefix.push(Step::Index(i));
                json_paths(child, prefix, out);
                prefix.pop();
            }
        }
        _ => {}
    }
}

fn json_at<'a>(v: &'a mut serde_json::Value, path: &[Step]) -> Option<&'a mut serde_json::Value> {
    path.iter().try_fold(v, |node, step| match step {
        Step::Key(k) => node.get_mut(k.as_str()),
        Step::Index(i) => node.get_mut(*i),
    })
}

impl Mutator {
    /// Structure-aware mutation of a JSON document (calibration and camera files): 1 to 4 edits
    /// that keep it valid JSON, so that the schema and the checks behind it are reached. Each
    /// edit picks a node and replaces a number by an interesting one, deletes an object member,
    /// shortens, empties or extends an array, copies another node's value over it (type and
    /// size confusion), or cuts or alters a string (base64 payloads). Returns `false` (and
    /// leaves `data` alone) when `data` is not JSON.
    pub fn mutate_json(&mut self, data: &mut Vec<u8>) -> bool {
        let Ok(mut doc) = serde_json::from_slice::<serde_json::Value>(data) else {
            return false;
        };
        for _ in 0..1 + self.below(4) {
            let mut paths = vec![];
            json_paths(&doc, &mut vec![], &mut paths);
            let path = paths[self.below(paths.len())].clone();
            let donor = json_at(&mut doc, &paths[self.below(paths.len())].clone()).cloned();
            let Some(node) = json_at(&mut doc, &path) else {
                continue;
            };
            match (self.below(4), node) {
                (0 | 1, node @ serde_json::Value::Number(_)) | (0, node) => {
                    let text = INTERESTING_JSON_NUMBERS[self.below(INTERESTING_JSON_NUMBERS.len())];
                    if let Ok(n) = serde_json::from_str::<serde_json::Value>(text) {
                        *node = n;
                    }
                }
                (1, serde_json::Value::Object(m)) if !m.is_empty() => {
                    let key = m.keys().nth(self.below(m.len())).cloned();
                    if let Some(key) = key {
                        m.remove(&key);
                    }
                }
                (1 | 2, serde_json::Value::Array(a)) => match self.below(3) {
                    0 => a.truncate(self.below(a.len() + 1)),
                    1 => a.clear(),
                    _ => {
                        if let Some(x) = a.first().cloned() {
                            let n = 1 + self.below(8);
                            a.extend(std::iter::repeat_n(x, n));
                        }
                    }
                },
                (1 | 2, serde_json::Value::String(text)) if !text.is_empty() => {
                    let mut bytes = std::mem::take(text).into_bytes();
                    let i = self.below(bytes.len());
                    if self.chance(0.5) {
                        bytes.truncate(i);
                    } else {
                        bytes[i] = b"A/+=-_ 0"[self.below(8)];
                    }
                    *text = String::from_utf8_lossy(&bytes).into_owned();
                }
                (_, node) => {
                    if let Some(d) = donor {
                        *node = d;
                    }
                }
            }
        }
        match serde_json::to_vec(&doc) {
            Ok(bytes) => {
                *data = bytes;
                true
            }
            Err(_) => false,
        }
    }
}

/// `[start, end)` of every maximal run of ASCII digits (with a leading `-`) in the first 64 KiB.
fn digit_runs(data: &[u8]) -> Vec<(usize, usize)> {
    let scan = &data[..data.len().min(64 << 10)];
    let mut runs = vec![];
    let mut i = 0;
    while i < scan.len() {
        if scan[i].is_ascii_digit() {
            let start = if i > 0 && scan[i - 1] == b'-' {
                i - 1
            } else {
                i
            };
            while i < scan.len() && (scan[i].is_ascii_digit() || scan[i] == b'.') {
                i += 1;
            }
            runs.push((start, i));
        } else {
            i += 1;
        }
    }
    runs
}

/// CRC-32 (ISO-HDLC), as PNG chunks use.
pub fn crc32(bytes: &[u8]) -> u32 {
    static TABLE: std::sync::OnceLock<[u32; 256]> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        let mut t = [0u32; 256];
        for (n, entry) in t.iter_mut().enumerate() {
            let mut c = n as u32;
            for _ in 0..8 {
                c = if c & 1 == 1 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
            *entry = c;
        }
        t
    });
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc = table[((crc ^ u32::from(b)) & 0xff) as usize] ^ (crc >> 8);
    }
    !crc
}

/// Recomputes the CRC of every complete chunk of a PNG, so mutated chunk data reaches the
/// decoder's later stages instead of failing the CRC check. Bytes that do not form chunks are
/// left as they are.
pub fn fix_png_crcs(data: &mut [u8]) {
    if data.len() < 8 || &data[..8] != b"\x89PNG\r\n\x1a\n" {
        return;
    }
    let mut pos = 8usize;
    while pos + 12 <= data.len() {
        let len = u32::from_be_bytes([data[pos], data[pos + 1], data[pos + 2], data[pos + 3]]);
        let Some(end) = usize::try_from(len)
            .ok()
            .and_then(|l| pos.checked_add(12)?.checked_add(l))
        else {
            return;
        };
        if end > data.len() {
            return;
        }
        let crc = crc32(&data[pos + 4..end - 4]);
        data[end - 4..end].copy_from_slice(&crc.to_be_bytes());
        pos = end;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_matches_the_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn mutations_are_deterministic_and_vary() {
        let seed = b"Pf\n2 3\n-1.0\nabcdefghijklmnopqrstuvwx".to_vec();
        let run = |i| {
            let mut d = seed.clone();
            Mutator::for_input(7, 1, i).mutate(&mut d, &[b"other seed"]);
            d
        };
        assert_eq!(run(3), run(3));
        let distinct: std::collections::HashSet<Vec<u8>> = (0..200).map(run).collect();
        assert!(distinct.len() > 150, "{}", distinct.len());
        assert!(
            (0..200)
                .map(run)
                .any(|d| d.windows(6).any(|w| w == b"100000"))
        );
    }

    #[test]
    fn json_mutations_keep_json_and_reach_every_kind_of_edit() {
        let seed = br#"{"a":{"n":1.5,"s":"QUJDRA==","v":[1,2,3]},"b":[{"x":0}],"c":true}"#;
        let mut changed = 0;
        let (mut numbers, mut shorter_arrays, mut strings) = (false, false, false);
        for i in 0..300 {
            let mut d = seed.to_vec();
            assert!(Mutator::for_input(1, 2, i).mutate_json(&mut d));
            let v: serde_json::Value = serde_json::from_slice(&d).expect("still JSON");
            changed += usize::from(d != seed);
            let text = String::from_utf8(d).unwrap();
            numbers |= INTERESTING_JSON_NUMBERS[6..]
                .iter()
                .any(|n| text.contains(n));
            shorter_arrays |= v["a"]["v"].as_array().is_some_and(|a| a.len() < 3);
            strings |= v["a"]["s"].as_str().is_some_and(|s| s != "QUJDRA==");
        }
        assert!(changed > 250, "{changed}");
        assert!(numbers && shorter_arrays && strings);
        // Not JSON: refused, untouched.
        let mut d = b"Pf\n".to_vec();
        assert!(!Mutator::for_input(1, 2, 0).mutate_json(&mut d));
        assert_eq!(d, b"Pf\n");
    }

    #[test]
    fn digit_runs_find_header_numbers() {
        assert_eq!(digit_runs(b"Pf\n12 -3\n"), vec![(3, 5), (6, 8)]);
    }
}
