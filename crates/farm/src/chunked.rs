//! Client-streaming uploads: one header message, then data parts of at most
//! [`MAX_CHUNK_BYTES`] each, exactly as many bytes in all as the header announces.
//!
//! Senders build the messages with [`messages`]; the coordinator reads them with [`header`]
//! and [`data`]. `UploadBlob`, `UploadTile` and `UploadRecords` share the reader so that the
//! three apply the same limits the same way; each maps a [`UploadError::Malformed`] to its
//! own answer (an `InvalidArgument` status, a corrupt tile ack, a refused records ack).

use pathfarm_proto::{v1, MAX_CHUNK_BYTES};
use tonic::{Status, Streaming};

/// One message of a chunked upload, as the reader sees it.
pub(crate) enum Part<H> {
    Header(H),
    Data(Vec<u8>),
}

/// A message type of a chunked upload: a `oneof part { Header header; bytes data; }`.
pub(crate) trait Chunked {
    type Header;
    /// The message's part; `None` when the oneof is unset.
    fn into_part(self) -> Option<Part<Self::Header>>;
    /// The message of `part`.
    fn from_part(part: Part<Self::Header>) -> Self;
}

/// The messages of one upload: the header, then the payloads one after the other in data
/// parts of at most `max` bytes (a part may hold the end of one payload and the start of
/// the next).
pub(crate) fn messages<M: Chunked>(header: M::Header, payloads: &[&[u8]], max: usize) -> Vec<M> {
    let max = max.max(1);
    let mut out = vec![M::from_part(Part::Header(header))];
    let mut part: Vec<u8> = Vec::new();
    for mut p in payloads.iter().copied() {
        while !p.is_empty() {
            let take = (max - part.len()).min(p.len());
            part.extend_from_slice(&p[..take]);
            p = &p[take..];
            if part.len() == max {
                out.push(M::from_part(Part::Data(std::mem::take(&mut part))));
            }
        }
    }
    if !part.is_empty() {
        out.push(M::from_part(Part::Data(part)));
    }
    out
}

/// Why an upload was not read.
#[derive(Debug)]
pub(crate) enum UploadError {
    /// The stream failed (the client went away, a transport error): answered as it is.
    Transport(Status),
    /// The messages break the upload's rules; the text says which.
    Malformed(String),
}

impl From<Status> for UploadError {
    fn from(s: Status) -> Self {
        UploadError::Transport(s)
    }
}

/// The upload's first message, which must be its header.
pub(crate) async fn header<M: Chunked>(
    stream: &mut Streaming<M>,
    rpc: &str,
) -> Result<M::Header, UploadError> {
    match stream.message().await?.and_then(M::into_part) {
        Some(Part::Header(h)) => Ok(h),
        _ => Err(UploadError::Malformed(format!(
            "the first message of {rpc} must be its header"
        ))),
    }
}

/// Reads the data parts after the header, handing each to `sink`, until the stream ends.
/// Refuses a part over [`MAX_CHUNK_BYTES`], a second header, more bytes than `size` (before
/// they reach `sink`) and, at the end, fewer.
pub(crate) async fn data<M: Chunked>(
    stream: &mut Streaming<M>,
    size: u64,
    mut sink: impl FnMut(&[u8]) -> Result<(), String>,
) -> Result<(), UploadError> {
    let malformed = |s: String| Err(UploadError::Malformed(s));
    let mut got = 0u64;
    while let Some(m) = stream.message().await? {
        let d = match m.into_part() {
            Some(Part::Data(d)) => d,
            _ => return malformed("a message after the header that is not a data part".into()),
        };
        if d.len() > MAX_CHUNK_BYTES {
            let n = d.len();
            return malformed(format!(
                "a data part of {n} bytes (at most {MAX_CHUNK_BYTES})"
            ));
        }
        got += d.len() as u64;
        if got > size {
            return malformed(format!("more data than the header's {size} bytes"));
        }
        sink(&d).map_err(UploadError::Malformed)?;
    }
    if got != size {
        return malformed(format!("{got} bytes of data, the header says {size}"));
    }
    Ok(())
}

/// [`data`] into memory; `size` is the caller's to bound before this allocates it.
pub(crate) async fn data_to_vec<M: Chunked>(
    stream: &mut Streaming<M>,
    size: u64,
) -> Result<Vec<u8>, UploadError> {
    let mut bytes = Vec::with_capacity(size as usize);
    data(stream, size, |d| {
        bytes.extend_from_slice(d);
        Ok(())
    })
    .await?;
    Ok(bytes)
}

macro_rules! chunked {
    ($msg:ty, $module:ident, $header:ty) => {
        impl Chunked for $msg {
            type Header = $header;
            fn into_part(self) -> Option<Part<$header>> {
                match self.part? {
                    v1::$module::Part::Header(h) => Some(Part::Header(h)),
                    v1::$module::Part::Data(d) => Some(Part::Data(d)),
                }
            }
            fn from_part(part: Part<$header>) -> Self {
                let part = match part {
                    Part::Header(h) => v1::$module::Part::Header(h),
                    Part::Data(d) => v1::$module::Part::Data(d),
                };
                Self { part: Some(part) }
            }
        }
    };
}

chunked!(v1::BlobChunk, blob_chunk, v1::BlobHeader);
chunked!(v1::TileUpload, tile_upload, v1::TileHeader);
chunked!(v1::RecordsUpload, records_upload, v1::RecordsHeader);
