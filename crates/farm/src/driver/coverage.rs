//! Which accepted uploads a holder's records are the sums of (`RecordsHeader.covered_*`).
//!
//! A worker's records of an iteration are right only if they hold exactly the records of the
//! uploads the coordinator accepted from it: one missing (a worker that dropped them, as a
//! late flush once did) or one too many gives a different guide, and so a different image,
//! with nothing to tell. Both sides add up the ids of those leases; records whose coverage
//! differs from what the coordinator accepted are refused, and the job rolls back.
//!
//! The digest is a sum (four wrapping u64 lanes of a hash of each lease id), so the order in
//! which the uploads were acknowledged does not matter, and a lease counted twice changes it.

use std::fmt;

/// The leases some records cover: how many, and the lanes of their digest.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Coverage {
    leases: u64,
    lanes: [u64; 4],
}

/// Bytes of [`Coverage::digest`].
pub const COVERAGE_DIGEST_BYTES: usize = 32;

/// A stated coverage digest of the wrong size.
#[derive(Debug, PartialEq, Eq, thiserror::Error)]
#[error("covered_digest is {0} bytes, not {COVERAGE_DIGEST_BYTES}")]
pub struct CoverageDigestLength(pub usize);

/// Domain separation: these hashes are of nothing else.
const DOMAIN: &[u8] = b"pathfarm records coverage v1";

impl Coverage {
    /// Counts lease `id`'s records in.
    pub fn add(&mut self, id: u64) {
        let mut h = blake3::Hasher::new();
        h.update(DOMAIN);
        h.update(&id.to_le_bytes());
        let bytes = h.finalize();
        for (lane, chunk) in self.lanes.iter_mut().zip(bytes.as_bytes().chunks_exact(8)) {
            let x = u64::from_le_bytes(chunk.try_into().expect("8 bytes"));
            *lane = lane.wrapping_add(x);
        }
        self.leases += 1;
    }

    /// The coverage of `ids`.
    pub fn of(ids: impl IntoIterator<Item = u64>) -> Self {
        let mut c = Coverage::default();
        ids.into_iter().for_each(|id| c.add(id));
        c
    }

    /// How many leases are covered.
    pub fn leases(&self) -> u64 {
        self.leases
    }

    /// The wire form of the digest: the lanes, little-endian.
    pub fn digest(&self) -> Vec<u8> {
        self.lanes.iter().flat_map(|l| l.to_le_bytes()).collect()
    }

    /// The coverage a header states: `leases` and a digest of [`COVERAGE_DIGEST_BYTES`].
    pub fn from_wire(leases: u64, digest: &[u8]) -> Result<Self, CoverageDigestLength> {
        if digest.len() != COVERAGE_DIGEST_BYTES {
            return Err(CoverageDigestLength(digest.len()));
        }
        let mut lanes = [0; 4];
        for (lane, chunk) in lanes.iter_mut().zip(digest.chunks_exact(8)) {
            *lane = u64::from_le_bytes(chunk.try_into().expect("8 bytes"));
        }
        Ok(Coverage { leases, lanes })
    }
}

/// "N leases (digest 0123abcd...)": the count and the digest's first 8 bytes, enough to
/// tell two coverages apart in a message.
impl fmt::Display for Coverage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let prefix: String = self.lanes[0]
            .to_le_bytes()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        write!(f, "{} leases (digest {prefix}...)", self.leases)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_order_of_the_leases_does_not_matter_and_each_one_counts() {
        let a = Coverage::of([3, 9, 27]);
        assert_eq!(a, Coverage::of([27, 3, 9]));
        assert_ne!(a, Coverage::of([3, 9]), "one missing");
        assert_ne!(a, Coverage::of([3, 9, 27, 27]), "one twice");
        assert_ne!(a, Coverage::of([3, 9, 28]), "another");
        // the digest alone tells a swap of the same count apart
        assert_ne!(a.digest(), Coverage::of([3, 9, 28]).digest());
    }

    #[test]
    fn the_wire_form_round_trips_and_a_bad_digest_is_named() {
        let c = Coverage::of([1, 2]);
        assert_eq!(Coverage::from_wire(c.leases(), &c.digest()), Ok(c));
        let e = Coverage::from_wire(2, &[0; 31]).unwrap_err();
        assert_eq!(e.to_string(), "covered_digest is 31 bytes, not 32");
        let shown = Coverage::from_wire(3, &[0xab; 32]).unwrap().to_string();
        assert_eq!(shown, "3 leases (digest abababababababab...)");
        assert_eq!(Coverage::default().digest(), vec![0; 32]);
    }
}
