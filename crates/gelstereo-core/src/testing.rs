//! Helpers of the property tests of every crate's file readers.

/// Applies byte edits to a file's contents, as a damaged or tampered file would differ: each
/// `(at, byte, kind)` picks the position `at` modulo one past the end, and with `kind` 0 replaces the
/// byte there, 1 inserts `byte` before it, anything else cuts the contents there.
pub fn mutate(bytes: &mut Vec<u8>, edits: &[(usize, u8, u8)]) {
    for &(at, byte, kind) in edits {
        let i = at % (bytes.len() + 1);
        match kind {
            0 if i < bytes.len() => bytes[i] = byte,
            1 => bytes.insert(i, byte),
            _ => bytes.truncate(i),
        }
    }
}
