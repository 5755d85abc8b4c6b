//! Structure fingerprints: a small FNV-1a hasher that trees feed their shape into, so that
//! statistics can be checked against the structure they were taken on.

/// FNV-1a 64-bit hasher used for structure fingerprints.
#[derive(Clone, Debug)]
pub struct Hasher64(u64);

impl Default for Hasher64 {
    fn default() -> Self {
        Self::new()
    }
}

impl Hasher64 {
    /// A fresh hasher.
    pub fn new() -> Self {
        Self(0xcbf2_9ce4_8422_2325)
    }
    /// Hashes bytes.
    pub fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    /// Hashes a u32 (little endian).
    pub fn write_u32(&mut self, v: u32) {
        self.write(&v.to_le_bytes());
    }
    /// Hashes a u64 (little endian).
    pub fn write_u64(&mut self, v: u64) {
        self.write(&v.to_le_bytes());
    }
    /// The hash value.
    pub fn finish(&self) -> u64 {
        self.0
    }
}
