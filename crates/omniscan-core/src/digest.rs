//! A 64-bit FNV-1a digest, to tell whether the inputs of a run changed
//! (a checkpoint's views, a pipeline stage's capture). Not for security:
//! ten lines of a public algorithm, where a hashing crate would add a
//! dependency for nothing the comparison needs.

/// FNV-1a over the bytes given, in order.
#[derive(Debug, Clone, Copy)]
pub struct Digest(u64);

impl Default for Digest {
    fn default() -> Self {
        Digest(0xcbf2_9ce4_8422_2325)
    }
}

impl Digest {
    pub fn add(&mut self, bytes: &[u8]) {
        for &byte in bytes {
            self.0 = (self.0 ^ byte as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }

    /// The digest as 16 hex digits.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }

    /// The digest of `bytes` alone, as hex.
    pub fn of(bytes: &[u8]) -> String {
        let mut d = Digest::default();
        d.add(bytes);
        d.hex()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_the_published_fnv1a_values() {
        assert_eq!(Digest::of(b""), "cbf29ce484222325");
        assert_eq!(Digest::of(b"a"), "af63dc4c8601ec8c");
        let mut split = Digest::default();
        split.add(b"fo");
        split.add(b"obar");
        assert_eq!(split.hex(), Digest::of(b"foobar"));
    }
}
