//! A [`Session`]'s state between iterations as bytes, so that a coordinator restarted on its
//! data directory resumes a job where its last finished iteration left it, with the bits an
//! uninterrupted run gives (the units after the checkpoint depend only on this state).
//!
//! A checkpoint comes in parts ([`Checkpoint`]): the state (magic `PFCK`, version byte, then
//! the fields in declaration order, little-endian), each film apart, and the tree in its own
//! wire form ([`SdTree::encode`]), so that a driver storing them by content writes a finished
//! iteration's film and a published tree once. Decoding checks every length (a checkpoint is
//! read back from disk, which may be damaged).

use std::sync::Arc;

use pathfarm_guide::schedule::IterationOutcome;
use pathfarm_guide::SdTree;

use crate::film::{Film, PixelStats};
use crate::guided::GuidedIteration;

const MAGIC: &[u8; 4] = b"PFCK";
const VERSION: u8 = 3;

/// A checkpoint that does not decode.
#[derive(Debug, thiserror::Error)]
#[error("session checkpoint: {0}")]
pub struct CheckpointError(pub String);

/// Little-endian writer.
#[derive(Default)]
pub(crate) struct Out(pub Vec<u8>);

impl Out {
    pub fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    pub fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    pub fn bytes(&mut self, b: &[u8]) {
        self.u64(b.len() as u64);
        self.0.extend_from_slice(b);
    }
    pub fn opt_u32(&mut self, v: Option<u32>) {
        self.u8(v.is_some() as u8);
        self.u32(v.unwrap_or(0));
    }
    pub fn opt_f64(&mut self, v: Option<f64>) {
        self.u8(v.is_some() as u8);
        self.f64(v.unwrap_or(0.0));
    }
    pub fn iteration(&mut self, i: &GuidedIteration) {
        self.u32(i.index);
        self.u32(i.spp);
        self.u64(i.nodes as u64);
        self.u64(i.leaves as u64);
        self.f64(i.variance);
        self.f64(i.seconds);
        self.f64(i.rays_per_sample);
        self.u8(i.training as u8);
    }
    pub fn outcome(&mut self, o: &IterationOutcome) {
        self.f64(o.variance);
        self.f64(o.cost);
        self.f64(o.remaining_before);
        self.u64(o.spp_before);
    }
}

/// Little-endian reader with length checks.
pub(crate) struct In<'a>(pub &'a [u8]);

impl In<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], CheckpointError> {
        if self.0.len() < n {
            return Err(CheckpointError("truncated".into()));
        }
        let (a, b) = self.0.split_at(n);
        self.0 = b;
        Ok(a)
    }
    pub fn u8(&mut self) -> Result<u8, CheckpointError> {
        Ok(self.take(1)?[0])
    }
    pub fn bool(&mut self) -> Result<bool, CheckpointError> {
        Ok(self.u8()? != 0)
    }
    pub fn u32(&mut self) -> Result<u32, CheckpointError> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }
    pub fn u64(&mut self) -> Result<u64, CheckpointError> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    pub fn f64(&mut self) -> Result<f64, CheckpointError> {
        Ok(f64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }
    pub fn len(&mut self, item: usize) -> Result<usize, CheckpointError> {
        let n = self.u64()? as usize;
        if n.checked_mul(item.max(1)).is_none_or(|b| b > self.0.len()) {
            return Err(CheckpointError(format!("length {n} beyond the data")));
        }
        Ok(n)
    }
    pub fn bytes(&mut self) -> Result<Vec<u8>, CheckpointError> {
        let n = self.len(1)?;
        Ok(self.take(n)?.to_vec())
    }
    pub fn opt_u32(&mut self) -> Result<Option<u32>, CheckpointError> {
        let some = self.bool()?;
        let v = self.u32()?;
        Ok(some.then_some(v))
    }
    pub fn opt_f64(&mut self) -> Result<Option<f64>, CheckpointError> {
        let some = self.bool()?;
        let v = self.f64()?;
        Ok(some.then_some(v))
    }
    pub fn film(&mut self) -> Result<Film, CheckpointError> {
        let (w, h) = (self.u32()?, self.u32()?);
        let n = w as usize * h as usize;
        let bytes = n.checked_mul(PixelStats::BYTES);
        if bytes.is_none_or(|b| b > self.0.len()) {
            return Err(CheckpointError(format!("film {w}x{h} beyond the data")));
        }
        let mut film = Film::new(w, h);
        for p in &mut film.pixels {
            *p = PixelStats::read_le(self.take(PixelStats::BYTES)?.try_into().unwrap());
        }
        Ok(film)
    }
    pub fn iteration(&mut self) -> Result<GuidedIteration, CheckpointError> {
        Ok(GuidedIteration {
            index: self.u32()?,
            spp: self.u32()?,
            nodes: self.u64()? as usize,
            leaves: self.u64()? as usize,
            variance: self.f64()?,
            seconds: self.f64()?,
            rays_per_sample: self.f64()?,
            training: self.bool()?,
        })
    }
    pub fn outcome(&mut self) -> Result<IterationOutcome, CheckpointError> {
        Ok(IterationOutcome {
            variance: self.f64()?,
            cost: self.f64()?,
            remaining_before: self.f64()?,
            spp_before: self.u64()?,
        })
    }
}

pub(crate) fn header(out: &mut Out) {
    out.0.extend_from_slice(MAGIC);
    out.u8(VERSION);
}

pub(crate) fn check_header(inp: &mut In) -> Result<(), CheckpointError> {
    let m = inp.take(5)?;
    if &m[..4] != MAGIC || m[4] != VERSION {
        return Err(CheckpointError("not a version-3 session checkpoint".into()));
    }
    Ok(())
}

/// A [`crate::session::Session`]'s checkpoint in parts: the films are most of its bytes, and
/// a finished iteration's film never changes, so a driver that stores the parts by content
/// writes each film once. The tree is saved beside it by the driver (its own wire form).
#[derive(Clone, Debug, PartialEq)]
pub struct Checkpoint {
    /// Everything but the films and the tree.
    pub state: Vec<u8>,
    /// The iteration films in order, then the path fallback's film ([`encode_film`]).
    pub films: Vec<Vec<u8>>,
}

/// A [`Checkpoint`] whose films are not encoded yet: the session's own films, shared
/// ([`crate::session::Session::checkpoint_parts`]).
#[derive(Clone, Debug)]
pub struct CheckpointParts {
    /// Everything but the films and the tree, as in [`Checkpoint::state`].
    pub state: Vec<u8>,
    /// The iteration films in order, then the path fallback's film.
    pub films: Vec<Arc<Film>>,
}

impl CheckpointParts {
    /// The checkpoint with every film encoded ([`encode_film`]).
    pub fn encode(self) -> Checkpoint {
        Checkpoint {
            state: self.state,
            films: self.films.iter().map(|f| encode_film(f)).collect(),
        }
    }
}

/// A film as checkpoint bytes: width, height, then every pixel's sums (exact bits).
pub fn encode_film(f: &Film) -> Vec<u8> {
    let mut out = Vec::with_capacity(8 + f.pixels.len() * PixelStats::BYTES);
    let to_vec = |piece: &[u8]| {
        out.extend_from_slice(piece);
        Ok::<(), std::convert::Infallible>(())
    };
    let Ok(()) = write_film(f, to_vec);
    out
}

/// Pixels a piece of [`write_film`] holds (under a megabyte).
const PIECE_PIXELS: usize = 8192;

/// [`encode_film`]'s bytes handed to `sink` a piece at a time: what a store writes to disk
/// without the whole encoding in memory (190 MB for a 1920x1080 film, freshly faulted in
/// at every checkpoint).
pub fn write_film<E>(f: &Film, mut sink: impl FnMut(&[u8]) -> Result<(), E>) -> Result<(), E> {
    let mut piece = Vec::with_capacity(8.max(PIECE_PIXELS * PixelStats::BYTES));
    piece.extend_from_slice(&f.width.to_le_bytes());
    piece.extend_from_slice(&f.height.to_le_bytes());
    sink(&piece)?;
    for pixels in f.pixels.chunks(PIECE_PIXELS) {
        piece.clear();
        pixels.iter().for_each(|p| p.write_le(&mut piece));
        sink(&piece)?;
    }
    Ok(())
}

/// Reads [`encode_film`]'s bytes of a `width x height` film.
pub fn decode_film(bytes: &[u8], width: u32, height: u32) -> Result<Film, CheckpointError> {
    let mut i = In(bytes);
    let f = i.film()?;
    if (f.width, f.height) != (width, height) || !i.0.is_empty() {
        return Err(CheckpointError(format!(
            "a film of {}x{} ({} bytes) for a {width}x{height} job",
            f.width,
            f.height,
            bytes.len()
        )));
    }
    Ok(f)
}

impl Checkpoint {
    /// The checkpoint and the tree's encoding as one byte string (a single-file form).
    pub fn to_bytes(&self, tree: &[u8]) -> Vec<u8> {
        let mut o = Out::default();
        header(&mut o);
        o.bytes(&self.state);
        o.u64(self.films.len() as u64);
        self.films.iter().for_each(|f| o.bytes(f));
        o.bytes(tree);
        o.0
    }

    /// Reads [`Checkpoint::to_bytes`]: the checkpoint and the tree.
    pub fn from_bytes(bytes: &[u8]) -> Result<(Checkpoint, SdTree), CheckpointError> {
        let mut i = In(bytes);
        check_header(&mut i)?;
        let state = i.bytes()?;
        let films = (0..i.len(8)?)
            .map(|_| i.bytes())
            .collect::<Result<_, _>>()?;
        let tree = decode_tree(&i.bytes()?)?;
        if !i.0.is_empty() {
            return Err(CheckpointError(format!(
                "{} bytes after the end",
                i.0.len()
            )));
        }
        Ok((Checkpoint { state, films }, tree))
    }
}

/// Reads a tree saved with a checkpoint.
pub fn decode_tree(bytes: &[u8]) -> Result<SdTree, CheckpointError> {
    SdTree::decode(bytes).map_err(|e| CheckpointError(format!("tree: {e}")))
}
