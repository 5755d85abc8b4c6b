//! Compact, versioned, checksummed binary forms of (a) a whole SD-tree and (b) one iteration's
//! statistics ([`crate::iteration_stats`]). Only encoding and decoding live here: this module
//! depends on the domain types, and nothing else in the crate depends on it.
//!
//! Frame layout (all integers little endian):
//! `magic[4] | version u16 | reserved u16 (0) | payload_len u64 | payload | crc32 u32`,
//! the CRC-32 (IEEE 802.3, reflected, poly 0xEDB88320) covering everything before it.
//! Magic `PFSD` = whole tree, `PFIS` = iteration statistics. Current version: [`VERSION`].
//! Fixed-point values are 128-bit integers with 48 fractional bits (see [`crate::stats`]).
//! Statistics' sums and quadtree sums are written compactly: a length byte `n` (0..=16) and
//! the value's `n` low bytes, no high zero byte (a sum of radiance near 1 takes 7-9 bytes
//! rather than 16: about 40 % fewer bytes per touched node); quadtree sums are stored
//! sparsely behind a 4-bit mask per node; a quadtree node's children as a second 4-bit mask
//! (in the same byte) and short distances between indices (v7; v6 wrote four `u32`s per
//! node, 40 % of a tree); a leaf's carried prior without the structure it shares with the
//! leaf's building tree.

use crate::config::{
    AdamConfig, DirectionalFilter, FractionLoss, FractionMode, GuideConfig, SpatialFilter,
};
use crate::dtree::{DNode, DTree, MAX_DEPTH};
use crate::fraction::{FractionState, GradAccum, GRID_LEN};
use crate::iteration_stats::{IterationStats, LeafStats};
use crate::light::LightStats;
use crate::sdtree::{Leaf, SdTree};
use crate::stats::Acc128;
use crate::stree::{SNode, STree};
use glam::Vec3;
use std::sync::atomic::AtomicU64;

/// Format version written by this crate.
pub const VERSION: u16 = 7;
/// Magic of a whole-tree frame.
pub const MAGIC_TREE: [u8; 4] = *b"PFSD";
/// Magic of an iteration-statistics frame.
pub const MAGIC_STATS: [u8; 4] = *b"PFIS";
const HEADER: usize = 4 + 2 + 2 + 8;

/// Decoding errors.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WireError {
    /// The first four bytes are not the expected magic.
    #[error("bad magic {0:?}")]
    BadMagic([u8; 4]),
    /// A version this crate cannot read.
    #[error("unsupported version {0}")]
    UnsupportedVersion(u16),
    /// The CRC-32 does not match the content.
    #[error("checksum mismatch (stored {stored:#010x}, computed {computed:#010x})")]
    ChecksumMismatch {
        /// CRC stored in the frame.
        stored: u32,
        /// CRC computed over the received bytes.
        computed: u32,
    },
    /// The input ends early (or the payload is shorter than a field needs).
    #[error("truncated input")]
    Truncated,
    /// The checksum matched but the content is inconsistent.
    #[error("malformed payload: {0}")]
    Malformed(&'static str),
}

// ---------------------------------------------------------------- checksums

/// CRC-32 (IEEE) of `data` (crc32fast: the hardware-assisted form; a byte-table loop cost a
/// farm's coordinator as much CPU as decoding the statistics it checks).
pub fn crc32(data: &[u8]) -> u32 {
    crc32fast::hash(data)
}

// ---------------------------------------------------------------- byte io

/// A frame under construction: the header's room first (filled in by [`frame`]), then the
/// payload, so that framing does not copy the payload.
struct W(Vec<u8>);
impl W {
    fn new() -> Self {
        W(vec![0; HEADER])
    }
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    /// `v` compactly: its byte length, then that many low bytes.
    fn cu128(&mut self, v: u128) {
        let n = (128 - v.leading_zeros()).div_ceil(8) as usize;
        self.0.push(n as u8);
        self.0.extend_from_slice(&v.to_le_bytes()[..n]);
    }
    /// `v` in LEB128: seven bits a byte, low first, the high bit set on all but the last.
    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push((v as u8 & 0x7f) | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }
    fn f32(&mut self, v: f32) {
        self.u32(v.to_bits());
    }
    fn f64(&mut self, v: f64) {
        self.u64(v.to_bits());
    }
}

struct R<'a> {
    b: &'a [u8],
    p: usize,
}
impl<'a> R<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], WireError> {
        if self.b.len() - self.p < n {
            return Err(WireError::Truncated);
        }
        let s = &self.b[self.p..self.p + n];
        self.p += n;
        Ok(s)
    }
    fn u8(&mut self) -> Result<u8, WireError> {
        Ok(self.take(1)?[0])
    }
    fn u32(&mut self) -> Result<u32, WireError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    fn u64(&mut self) -> Result<u64, WireError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    fn f32(&mut self) -> Result<f32, WireError> {
        Ok(f32::from_bits(self.u32()?))
    }
    fn f64(&mut self) -> Result<f64, WireError> {
        Ok(f64::from_bits(self.u64()?))
    }
    /// A value written by `W::cu128`; only its one (canonical) form is accepted, so that
    /// re-encoding a decoded frame gives the same bytes.
    fn cu128(&mut self) -> Result<u128, WireError> {
        let n = self.u8()? as usize;
        if n > 16 {
            return Err(WireError::Malformed("compact integer length"));
        }
        let b = self.take(n)?;
        if b.last() == Some(&0) {
            return Err(WireError::Malformed(
                "compact integer with a high zero byte",
            ));
        }
        let mut le = [0u8; 16];
        le[..n].copy_from_slice(b);
        Ok(u128::from_le_bytes(le))
    }
    /// A value written by `W::varint`, of at most 5 bytes (35 bits: child distances are
    /// `u32`s), in its one shortest form.
    fn varint(&mut self) -> Result<u64, WireError> {
        let mut v = 0u64;
        for k in 0..5 {
            let b = self.u8()?;
            v |= u64::from(b & 0x7f) << (7 * k);
            if b & 0x80 == 0 {
                if b == 0 && k > 0 {
                    return Err(WireError::Malformed("variable-length integer not shortest"));
                }
                return Ok(v);
            }
        }
        Err(WireError::Malformed("variable-length integer too long"))
    }
    fn cu128s(&mut self) -> Result<[u128; GRID_LEN], WireError> {
        let mut v = [0u128; GRID_LEN];
        for x in &mut v {
            *x = self.cu128()?;
        }
        Ok(v)
    }
    /// A count that must be plausible given the bytes left (each element >= `min_size` bytes).
    fn count(&mut self, min_size: usize) -> Result<usize, WireError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(min_size) > self.b.len() - self.p {
            return Err(WireError::Truncated);
        }
        Ok(n)
    }
}

fn frame(magic: [u8; 4], payload: W) -> Vec<u8> {
    let mut out = payload.0;
    let len = (out.len() - HEADER) as u64;
    out[..4].copy_from_slice(&magic);
    out[4..6].copy_from_slice(&VERSION.to_le_bytes());
    out[6..8].copy_from_slice(&0u16.to_le_bytes());
    out[8..16].copy_from_slice(&len.to_le_bytes());
    let c = crc32(&out);
    out.extend_from_slice(&c.to_le_bytes());
    out
}

fn unframe(magic: [u8; 4], bytes: &[u8]) -> Result<&[u8], WireError> {
    if bytes.len() < 4 {
        return Err(WireError::Truncated);
    }
    let m: [u8; 4] = bytes[..4].try_into().unwrap();
    if m != magic {
        return Err(WireError::BadMagic(m));
    }
    if bytes.len() < HEADER + 4 {
        return Err(WireError::Truncated);
    }
    let version = u16::from_le_bytes([bytes[4], bytes[5]]);
    if version != VERSION {
        return Err(WireError::UnsupportedVersion(version));
    }
    let len = u64::from_le_bytes(bytes[8..16].try_into().unwrap());
    let avail = (bytes.len() - HEADER - 4) as u64;
    if len > avail {
        return Err(WireError::Truncated);
    }
    let end = HEADER + len as usize;
    let stored = u32::from_le_bytes(bytes[end..end + 4].try_into().unwrap());
    let computed = crc32(&bytes[..end]);
    if stored != computed {
        return Err(WireError::ChecksumMismatch { stored, computed });
    }
    if len < avail {
        return Err(WireError::Malformed("trailing bytes after the frame"));
    }
    if bytes[6] != 0 || bytes[7] != 0 {
        return Err(WireError::Malformed("reserved header field is not zero"));
    }
    Ok(&bytes[HEADER..end])
}

// ---------------------------------------------------------------- tree

fn put_config(w: &mut W, c: &GuideConfig) {
    w.f64(c.s_tree_threshold);
    w.f64(c.d_tree_threshold);
    w.u32(c.max_d_tree_depth);
    w.u32(c.spp_per_pass);
    w.u8(match c.spatial_filter {
        SpatialFilter::Nearest => 0,
        SpatialFilter::Stochastic => 1,
        SpatialFilter::Box => 2,
    });
    w.u8(match c.directional_filter {
        DirectionalFilter::Nearest => 0,
        DirectionalFilter::Box => 1,
    });
    match c.bsdf_sampling_fraction {
        FractionMode::Fixed(a) => {
            w.u8(0);
            w.f32(a);
        }
        FractionMode::Learned { loss } => {
            w.u8(1);
            w.u32(match loss {
                FractionLoss::Kl => 0,
                FractionLoss::Var => 1,
            });
        }
    }
    w.f32(c.fraction_clamp.0);
    w.f32(c.fraction_clamp.1);
    let a = &c.adam;
    for v in [
        a.learning_rate,
        a.beta1,
        a.beta2,
        a.epsilon,
        a.l2,
        a.min_batch_weight,
        a.gradient_clamp,
    ] {
        w.f64(v);
    }
    w.u64(c.max_nodes.map(|n| n as u64).unwrap_or(u64::MAX));
    w.f64(c.carry_over);
}

fn get_config(r: &mut R) -> Result<GuideConfig, WireError> {
    let s_tree_threshold = r.f64()?;
    let d_tree_threshold = r.f64()?;
    let max_d_tree_depth = r.u32()?;
    let spp_per_pass = r.u32()?;
    let spatial_filter = match r.u8()? {
        0 => SpatialFilter::Nearest,
        1 => SpatialFilter::Stochastic,
        2 => SpatialFilter::Box,
        _ => return Err(WireError::Malformed("spatial filter")),
    };
    let directional_filter = match r.u8()? {
        0 => DirectionalFilter::Nearest,
        1 => DirectionalFilter::Box,
        _ => return Err(WireError::Malformed("directional filter")),
    };
    let bsdf_sampling_fraction = match r.u8()? {
        0 => FractionMode::Fixed(r.f32()?),
        1 => FractionMode::Learned {
            loss: match r.u32()? {
                0 => FractionLoss::Kl,
                1 => FractionLoss::Var,
                _ => return Err(WireError::Malformed("fraction loss")),
            },
        },
        _ => return Err(WireError::Malformed("fraction mode")),
    };
    let fraction_clamp = (r.f32()?, r.f32()?);
    let adam = AdamConfig {
        learning_rate: r.f64()?,
        beta1: r.f64()?,
        beta2: r.f64()?,
        epsilon: r.f64()?,
        l2: r.f64()?,
        min_batch_weight: r.f64()?,
        gradient_clamp: r.f64()?,
    };
    let mn = r.u64()?;
    let carry_over = r.f64()?;
    if max_d_tree_depth == 0 || max_d_tree_depth > MAX_DEPTH {
        return Err(WireError::Malformed("quadtree depth"));
    }
    if !(0.0..=1.0).contains(&carry_over) {
        return Err(WireError::Malformed("carry-over fraction"));
    }
    Ok(GuideConfig {
        s_tree_threshold,
        d_tree_threshold,
        max_d_tree_depth,
        spp_per_pass,
        spatial_filter,
        directional_filter,
        bsdf_sampling_fraction,
        fraction_clamp,
        adam,
        max_nodes: if mn == u64::MAX {
            None
        } else {
            Some(mn as usize)
        },
        max_dtree_nodes: None,
        carry_over,
    })
}

fn put_sums(w: &mut W, sums: &[u128; 4]) {
    put_sums_with(w, sums, 0);
}

/// The sums behind their 4-bit mask, `high` (a high nibble) or-ed into the mask's byte.
fn put_sums_with(w: &mut W, sums: &[u128; 4], high: u8) {
    let mut mask = high;
    for (q, &s) in sums.iter().enumerate() {
        if s != 0 {
            mask |= 1 << q;
        }
    }
    w.u8(mask);
    for &s in sums {
        if s != 0 {
            w.cu128(s);
        }
    }
}

fn get_sums(r: &mut R) -> Result<[u128; 4], WireError> {
    let (s, high) = get_sums_with(r)?;
    if high != 0 {
        return Err(WireError::Malformed("sum mask"));
    }
    Ok(s)
}

/// The sums written by [`put_sums_with`] and the high nibble of their mask's byte.
fn get_sums_with(r: &mut R) -> Result<([u128; 4], u8), WireError> {
    let byte = r.u8()?;
    let mask = byte & 15;
    let mut s = [0u128; 4];
    for (q, v) in s.iter_mut().enumerate() {
        if mask & (1 << q) != 0 {
            *v = r.cu128()?;
            if *v == 0 {
                return Err(WireError::Malformed("a zero sum under the mask"));
            }
        }
    }
    Ok((s, byte >> 4))
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    ((v >> 1) as i64) ^ -((v & 1) as i64)
}

fn put_dtree(w: &mut W, t: &DTree) {
    w.cu128(t.weight.get());
    w.u32(t.nodes.len() as u32);
    for (i, n) in t.nodes.iter().enumerate() {
        let sums = n.sums_fixed();
        let child_mask = (0..4).fold(0u8, |m, q| m | (u8::from(n.children[q] != 0) << q));
        put_sums_with(w, &sums, child_mask << 4);
        put_children(w, i as u32, &n.children);
    }
}

fn put_children(w: &mut W, i: u32, children: &[u32; 4]) {
    let mut prev: Option<u32> = None;
    for &c in children.iter().filter(|&&c| c != 0) {
        match prev {
            None => w.varint(u64::from(c - i - 1)),
            Some(p) => w.varint(zigzag(i64::from(c) - i64::from(p) - 1)),
        }
        prev = Some(c);
    }
}

/// A quadtree's nodes without their children (the structure is another tree's: a leaf's
/// carried prior has its building tree's).
fn put_dtree_sums(w: &mut W, t: &DTree) {
    w.cu128(t.weight.get());
    for n in &t.nodes {
        put_sums(w, &n.sums_fixed());
    }
}

fn get_dtree(r: &mut R) -> Result<DTree, WireError> {
    let weight = r.cu128()?;
    let n = r.count(1)?;
    if n == 0 {
        return Err(WireError::Malformed("empty quadtree"));
    }
    let mut nodes = Vec::with_capacity(n);
    let mut seen = vec![false; n];
    for i in 0..n {
        let (sums, child_mask) = get_sums_with(r)?;
        let children = get_children(r, i, child_mask, &mut seen)?;
        nodes.push(DNode {
            sums: sums.map(Acc128::from_u128),
            children,
        });
    }
    if seen.iter().skip(1).any(|&s| !s) {
        return Err(WireError::Malformed("unreachable quadtree node"));
    }
    let t = DTree {
        nodes,
        weight: Acc128::from_u128(weight),
    };
    if t.depth() > MAX_DEPTH {
        return Err(WireError::Malformed("quadtree too deep"));
    }
    Ok(t)
}

/// Node `i`'s children (`mask`: which quadrants have one); each must lie after `i`, inside
/// the tree, and be nobody else's child.
fn get_children(r: &mut R, i: usize, mask: u8, seen: &mut [bool]) -> Result<[u32; 4], WireError> {
    let mut children = [0u32; 4];
    let mut prev: Option<i64> = None;
    for (q, c) in children.iter_mut().enumerate() {
        if mask & (1 << q) == 0 {
            continue;
        }
        let ci = match prev {
            None => i as i64 + 1 + r.varint()? as i64,
            Some(p) => p + 1 + unzigzag(r.varint()?),
        };
        if ci <= i as i64 || ci >= seen.len() as i64 || seen[ci as usize] {
            return Err(WireError::Malformed("quadtree child index"));
        }
        seen[ci as usize] = true;
        *c = ci as u32;
        prev = Some(ci);
    }
    Ok(children)
}

/// A prior: `0` none (an empty quadtree), `1` the building tree's structure with these
/// sums, `2` a structure of its own (which decoding rejects: see [`carry::fits`]).
///
/// [`carry::fits`]: crate::carry::fits
fn put_prior(w: &mut W, prior: &DTree, building: &DTree) {
    if crate::carry::is_empty(prior) {
        w.u8(0);
    } else if crate::carry::fits(prior, building) {
        w.u8(1);
        put_dtree_sums(w, prior);
    } else {
        w.u8(2);
        put_dtree(w, prior);
    }
}

fn get_prior(r: &mut R, building: &DTree) -> Result<DTree, WireError> {
    match r.u8()? {
        0 => Ok(DTree::new()),
        1 => {
            let weight = Acc128::from_u128(r.cu128()?);
            let mut nodes = Vec::with_capacity(building.nodes.len());
            for b in &building.nodes {
                let sums = get_sums(r)?.map(Acc128::from_u128);
                let children = b.children;
                nodes.push(DNode { sums, children });
            }
            let prior = DTree { nodes, weight };
            if crate::carry::is_empty(&prior) {
                return Err(WireError::Malformed("an empty prior in the shared form"));
            }
            Ok(prior)
        }
        2 => get_dtree(r),
        _ => Err(WireError::Malformed("prior form")),
    }
}

impl SdTree {
    /// Serialises the whole tree (configuration, S-tree, both quadtrees of every leaf, fraction
    /// state, pending statistics) into a `PFSD` frame. `decode(encode(t)) == t` bit for bit.
    pub fn encode(&self) -> Vec<u8> {
        let mut w = W::new();
        put_config(&mut w, &self.config);
        let s = &self.stree;
        w.f32(s.min.x);
        w.f32(s.min.y);
        w.f32(s.min.z);
        w.f32(s.size);
        w.u8(self.built as u8);
        w.u64(self.overflow_events());
        w.u32(s.nodes.len() as u32);
        for n in &s.nodes {
            w.u8(n.axis);
            w.u32(n.children[0]);
            w.u32(n.children[1]);
            w.u32(n.leaf);
            w.u32(n.depth);
        }
        w.u32(self.leaves.len() as u32);
        put_leaves(&mut w, &self.leaves);
        frame(MAGIC_TREE, w)
    }

    /// Parses a `PFSD` frame produced by [`SdTree::encode`].
    pub fn decode(bytes: &[u8]) -> Result<SdTree, WireError> {
        let payload = unframe(MAGIC_TREE, bytes)?;
        let mut r = R { b: payload, p: 0 };
        let config = get_config(&mut r)?;
        let min = Vec3::new(r.f32()?, r.f32()?, r.f32()?);
        let size = r.f32()?;
        let built = match r.u8()? {
            0 => false,
            1 => true,
            _ => return Err(WireError::Malformed("built flag")),
        };
        let overflow = r.u64()?;
        let nn = r.count(17)?;
        let mut nodes = Vec::with_capacity(nn);
        for _ in 0..nn {
            nodes.push(SNode {
                axis: r.u8()?,
                children: [r.u32()?, r.u32()?],
                leaf: r.u32()?,
                depth: r.u32()?,
            });
        }
        // (a leaf takes at least 32 + 18 + 4 + 3 + 8 bytes, two 6-byte quadtrees, a prior tag)
        let nl = r.count(78)?;
        // validate the S-tree
        if nn == 0 || !(size > 0.0) || !min.is_finite() {
            return Err(WireError::Malformed("spatial domain"));
        }
        if nodes[0].axis != 0 || nodes[0].depth != 0 {
            return Err(WireError::Malformed("spatial root"));
        }
        let mut leaf_seen = vec![false; nl];
        let mut node_seen = vec![false; nn];
        for (i, n) in nodes.iter().enumerate() {
            if n.axis > 2 {
                return Err(WireError::Malformed("split axis"));
            }
            if n.is_leaf() {
                if n.children[1] != 0 || (n.leaf as usize) >= nl || leaf_seen[n.leaf as usize] {
                    return Err(WireError::Malformed("spatial leaf index"));
                }
                leaf_seen[n.leaf as usize] = true;
            } else {
                for &c in &n.children {
                    let c = c as usize;
                    if c <= i || c >= nn || node_seen[c] {
                        return Err(WireError::Malformed("spatial child index"));
                    }
                    node_seen[c] = true;
                    // Children split on the next axis, one level deeper, within the depth
                    // limit (lookups rely on at most 20 splits per axis).
                    let k = &nodes[c];
                    if k.axis != (n.axis + 1) % 3
                        || k.depth != n.depth + 1
                        || k.depth > crate::sdtree::MAX_SPATIAL_DEPTH
                    {
                        return Err(WireError::Malformed("spatial split axis or depth"));
                    }
                }
            }
        }
        if leaf_seen.iter().any(|&s| !s) || node_seen.iter().skip(1).any(|&s| !s) {
            return Err(WireError::Malformed("spatial tree is not a tree"));
        }
        let mut leaves = Vec::with_capacity(nl);
        for _ in 0..nl {
            let fraction = FractionState {
                theta: r.f64()?,
                m: r.f64()?,
                v: r.f64()?,
                t: r.u64()?,
            };
            let grad = GradAccum {
                pos: r.cu128s()?.map(Acc128::from_u128),
                neg: r.cu128s()?.map(Acc128::from_u128),
                weight: Acc128::from_u128(r.cu128()?),
                stepped: Acc128::from_u128(r.cu128()?),
            };
            let flux = r.f32()?;
            if !(flux >= 0.0 && flux.is_finite()) {
                return Err(WireError::Malformed("leaf flux"));
            }
            let light = LightStats {
                sum: Acc128::from_u128(r.cu128()?),
                sum_sq: Acc128::from_u128(r.cu128()?),
                count: Acc128::from_u128(r.cu128()?),
                mean: r.f32()?,
                std_dev: r.f32()?,
            };
            if !(light.mean >= 0.0
                && light.mean.is_finite()
                && light.std_dev >= 0.0
                && light.std_dev.is_finite())
            {
                return Err(WireError::Malformed("leaf light statistics"));
            }
            let building = get_dtree(&mut r)?;
            let sampling = get_dtree(&mut r)?.freeze();
            let prior = get_prior(&mut r, &building)?;
            // Carried statistics fit the building tree's structure, or there are none.
            if !crate::carry::fits(&prior, &building) {
                return Err(WireError::Malformed("carried statistics' structure"));
            }
            leaves.push(Leaf {
                building,
                sampling,
                fraction,
                grad,
                held: Default::default(),
                flux,
                alpha: crate::sdtree::alpha_of(fraction.theta),
                light,
                prior,
            });
        }
        if r.p != payload.len() {
            return Err(WireError::Malformed("trailing payload bytes"));
        }
        Ok(SdTree {
            config,
            stree: STree::from_parts(min, size, nodes),
            leaves,
            built,
            overflow: AtomicU64::new(overflow),
            nonfinite: AtomicU64::new(0),
            raised_rho: None,
            hash: Default::default(),
            touched: crate::sdtree::TouchedLeaves::new(nl),
            grad_target: Default::default(),
        })
    }
}

/// Leaves below which a tree is encoded on the calling thread alone.
const LEAVES_PER_ENCODER: usize = 256;

/// Appends every leaf's encoding, in order. A big tree's leaves are encoded in chunks on
/// several threads (a farm encodes each new tree while every worker waits for it), each
/// chunk into its own buffer, appended in order: the bytes are those of one thread.
fn put_leaves(w: &mut W, leaves: &[Leaf]) {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = cores.min(leaves.len() / LEAVES_PER_ENCODER).max(1);
    if threads == 1 {
        leaves.iter().for_each(|l| put_leaf(w, l));
        return;
    }
    let chunk = leaves.len().div_ceil(threads);
    let parts: Vec<Vec<u8>> = std::thread::scope(|scope| {
        let encoders: Vec<_> = leaves
            .chunks(chunk)
            .map(|c| {
                scope.spawn(move || {
                    let mut part = W(Vec::with_capacity(c.iter().map(leaf_bytes_bound).sum()));
                    c.iter().for_each(|l| put_leaf(&mut part, l));
                    part.0
                })
            })
            .collect();
        let joined = encoders.into_iter().map(|e| e.join());
        joined
            .map(|r| r.expect("encoding a leaf cannot panic"))
            .collect()
    });
    w.0.reserve(parts.iter().map(Vec::len).sum::<usize>() + 4);
    parts.iter().for_each(|p| w.0.extend_from_slice(p));
}

/// About the most bytes [`put_leaf`] writes for `l` (a capacity to reserve: a tree of a
/// million nodes grown by doubling was copied and faulted in several times over). A node
/// with sums writes a mask byte, its non-zero sums (at most 17 bytes each) and its child
/// distances; a building tree's nodes have no sums while the tree is published.
fn leaf_bytes_bound(l: &Leaf) -> usize {
    let sampling = l.sampling.tree().node_count();
    let building = l.building.node_count();
    let prior = if crate::carry::is_empty(&l.prior) {
        0
    } else {
        l.prior.node_count()
    };
    256 + 48 * sampling + 8 * building + 40 * prior
}

fn put_leaf(w: &mut W, l: &Leaf) {
    let f = &l.fraction;
    w.f64(f.theta);
    w.f64(f.m);
    w.f64(f.v);
    w.u64(f.t);
    for a in l.grad.pos.iter().chain(l.grad.neg.iter()) {
        w.cu128(a.get());
    }
    w.cu128(l.grad.weight.get());
    w.cu128(l.grad.stepped.get());
    w.f32(l.flux);
    for x in l.light.sums() {
        w.cu128(x);
    }
    w.f32(l.light.mean);
    w.f32(l.light.std_dev);
    put_dtree(w, &l.building);
    put_dtree(w, l.sampling.tree());
    put_prior(w, &l.prior, &l.building);
}

// ---------------------------------------------------------------- statistics

impl IterationStats {
    /// Serialises into a `PFIS` frame.
    pub fn encode(&self) -> Vec<u8> {
        let mut w = W::new();
        w.u64(self.structure_hash);
        w.u64(self.overflow_events);
        w.u32(self.leaves.len() as u32);
        for l in &self.leaves {
            w.u32(l.leaf);
            w.cu128(l.weight);
            for x in l.grad_pos.iter().chain(l.grad_neg.iter()) {
                w.cu128(*x);
            }
            w.cu128(l.grad_weight);
            for x in l.light {
                w.cu128(x);
            }
            w.u32(l.nodes.len() as u32);
            for (n, s) in &l.nodes {
                w.u32(*n);
                put_sums(&mut w, s);
            }
        }
        frame(MAGIC_STATS, w)
    }

    /// Parses a `PFIS` frame produced by [`IterationStats::encode`].
    pub fn decode(bytes: &[u8]) -> Result<IterationStats, WireError> {
        let payload = unframe(MAGIC_STATS, bytes)?;
        let mut r = R { b: payload, p: 0 };
        let structure_hash = r.u64()?;
        let overflow_events = r.u64()?;
        // (a leaf takes at least 4 + 1 + 2 GRID_LEN + 1 + 3 + 4 bytes)
        let nl = r.count(13 + 2 * GRID_LEN)?;
        let mut leaves: Vec<LeafStats> = Vec::with_capacity(nl);
        for _ in 0..nl {
            let leaf = r.u32()?;
            if leaves.last().is_some_and(|p| p.leaf >= leaf) {
                return Err(WireError::Malformed("leaves not ascending"));
            }
            let mut ls = LeafStats {
                leaf,
                weight: r.cu128()?,
                grad_pos: r.cu128s()?,
                grad_neg: r.cu128s()?,
                grad_weight: r.cu128()?,
                light: [r.cu128()?, r.cu128()?, r.cu128()?],
                nodes: Vec::new(),
            };
            let nn = r.count(5)?;
            // (one allocation a leaf: growing by pushes was a third of the decode's time)
            ls.nodes.reserve_exact(nn);
            for _ in 0..nn {
                let n = r.u32()?;
                if ls.nodes.last().is_some_and(|p| p.0 >= n) {
                    return Err(WireError::Malformed("nodes not ascending"));
                }
                ls.nodes.push((n, get_sums(&mut r)?));
            }
            leaves.push(ls);
        }
        if r.p != payload.len() {
            return Err(WireError::Malformed("trailing payload bytes"));
        }
        Ok(IterationStats {
            structure_hash,
            overflow_events,
            leaves,
        })
    }
}

#[cfg(test)]
mod tests;
