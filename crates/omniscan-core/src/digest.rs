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

/// `value` with every fractional number written to 12 significant digits,
/// to digest what a JSON file says rather than its last bits:
/// a pose read from `capture.json` and written back moves in its last bits
/// (rotation matrix to quaternion and back), which is no change of input.
pub fn stable_json(value: serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match value {
        Value::Number(n) if n.is_f64() => {
            Value::String(format!("{:.11e}", n.as_f64().unwrap_or(0.0)))
        }
        Value::Array(items) => Value::Array(items.into_iter().map(stable_json).collect()),
        Value::Object(map) => {
            Value::Object(map.into_iter().map(|(k, v)| (k, stable_json(v))).collect())
        }
        other => other,
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

    #[test]
    fn stable_json_ignores_the_last_bits_of_a_number_and_nothing_more() {
        let a =
            serde_json::json!({"pose": [0.20475304505920647, 1, -0.1698535483567055], "n": "x"});
        let b =
            serde_json::json!({"pose": [0.2047530450592065, 1, -0.16985354835670546], "n": "x"});
        let c = serde_json::json!({"pose": [0.2047530451, 1, -0.1698535483567055], "n": "x"});
        assert_eq!(stable_json(a.clone()), stable_json(b));
        assert_ne!(stable_json(a), stable_json(c));
    }
}
