//! Client-streaming uploads: one header message, then data parts of at most
//! [`MAX_CHUNK_BYTES`] each, exactly as many bytes in all as the header announces.
//!
//! Senders build the messages with [`messages`]; the coordinator reads them with [`header`]
//! and [`data`]. `UploadBlob`, `UploadTile` and `UploadRecords` share the reader so that the
//! three apply the same limits the same way; each maps a [`UploadError::Malformed`] to its
//! own answer (an `InvalidArgument` status, a corrupt tile ack, a refused records ack).

use std::time::Duration;

use pathfarm_proto::{v1, MAX_CHUNK_BYTES};
use tokio_stream::{Stream, StreamExt};
use tonic::Status;

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
    /// No message came within the idle timeout.
    Idle(Duration),
}

impl UploadError {
    /// As a status: a malformed upload is `InvalidArgument`, an idle one `DeadlineExceeded`.
    pub(crate) fn into_status(self) -> Status {
        match self {
            UploadError::Transport(s) => s,
            UploadError::Malformed(detail) => Status::invalid_argument(detail),
            UploadError::Idle(d) => Status::deadline_exceeded(format!(
                "the upload sent nothing for {} s",
                d.as_secs_f64()
            )),
        }
    }
}

/// An upload's messages as the server receives them (`tonic::Streaming`, or any stream in
/// tests).
pub(crate) trait Messages<M>: Stream<Item = Result<M, Status>> + Unpin {}

impl<M, S: Stream<Item = Result<M, Status>> + Unpin> Messages<M> for S {}

/// The stream's next message, waiting at most `idle`.
async fn next<M>(stream: &mut impl Messages<M>, idle: Duration) -> Result<Option<M>, UploadError> {
    match tokio::time::timeout(idle, stream.next()).await {
        Ok(m) => Ok(m.transpose()?),
        Err(_) => Err(UploadError::Idle(idle)),
    }
}

impl From<Status> for UploadError {
    fn from(s: Status) -> Self {
        UploadError::Transport(s)
    }
}

/// The upload's first message, which must be its header.
pub(crate) async fn header<M: Chunked>(
    stream: &mut impl Messages<M>,
    rpc: &str,
    idle: Duration,
) -> Result<M::Header, UploadError> {
    match next(stream, idle).await?.and_then(M::into_part) {
        Some(Part::Header(h)) => Ok(h),
        _ => Err(UploadError::Malformed(format!(
            "the first message of {rpc} must be its header"
        ))),
    }
}

/// Reads the data parts after the header, handing each to `sink`, until the stream ends.
/// Refuses a part over [`MAX_CHUNK_BYTES`], a second header, more bytes than `size` (before
/// they reach `sink`) and, at the end, fewer; gives up when no message comes within `idle`.
pub(crate) async fn data<M: Chunked>(
    stream: &mut impl Messages<M>,
    size: u64,
    idle: Duration,
    mut sink: impl FnMut(&[u8]) -> Result<(), String>,
) -> Result<(), UploadError> {
    let malformed = |s: String| Err(UploadError::Malformed(s));
    let mut got = 0u64;
    while let Some(m) = next(stream, idle).await? {
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

/// [`data`] into memory; `size` is the caller's to bound (and reserve) before this reads
/// it. The buffer grows with the data received, never ahead of it by more than a part.
pub(crate) async fn data_to_vec<M: Chunked>(
    stream: &mut impl Messages<M>,
    size: u64,
    idle: Duration,
) -> Result<Vec<u8>, UploadError> {
    let mut bytes = Vec::with_capacity(size.min(MAX_CHUNK_BYTES as u64) as usize);
    data(stream, size, idle, |d| {
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

#[cfg(test)]
mod tests {
    use super::*;

    type Msg = v1::RecordsUpload;

    fn head(size: u64) -> Result<Msg, Status> {
        let h = v1::RecordsHeader {
            size,
            ..Default::default()
        };
        Ok(Msg::from_part(Part::Header(h)))
    }

    fn data(d: Vec<u8>) -> Result<Msg, Status> {
        Ok(Msg::from_part(Part::Data(d)))
    }

    const IDLE: Duration = Duration::from_secs(5);

    /// Reads `msgs` as an upload of 3 bytes: its data, or the refusal's text.
    async fn read(msgs: Vec<Result<Msg, Status>>) -> Result<Vec<u8>, String> {
        let mut s = tokio_stream::iter(msgs);
        let h = header_of(&mut s).await?;
        data_to_vec(&mut s, h.size, IDLE)
            .await
            .map_err(|e| match e {
                UploadError::Malformed(m) => m,
                e => format!("{:?}", e.into_status()),
            })
    }

    async fn header_of(s: &mut impl Messages<Msg>) -> Result<v1::RecordsHeader, String> {
        super::header(s, "UploadRecords", IDLE)
            .await
            .map_err(|e| match e {
                UploadError::Malformed(m) => m,
                e => format!("{:?}", e.into_status()),
            })
    }

    #[tokio::test]
    async fn the_reader_refuses_oversized_parts_wrong_lengths_and_a_second_header() {
        let over = vec![0u8; MAX_CHUNK_BYTES + 1];
        let cases: [(Vec<Vec<u8>>, &str); 4] = [
            (vec![over], "a data part of"),
            (vec![vec![1, 2], vec![3, 4]], "more data than"),
            (vec![vec![1, 2]], "2 bytes of data, the header says 3"),
            (vec![], "0 bytes of data"),
        ];
        for (parts, names) in cases {
            let msgs = std::iter::once(head(3)).chain(parts.into_iter().map(data));
            let e = read(msgs.collect()).await.unwrap_err();
            assert!(e.contains(names), "{names:?}: {e}");
        }
        let e = read(vec![head(3), head(3)]).await.unwrap_err();
        assert!(e.contains("not a data part"), "{e}");
        let e = read(vec![data(vec![1])]).await.unwrap_err();
        assert!(e.contains("must be its header"), "{e}");
        let ok = read(vec![head(3), data(vec![1, 2]), data(vec![3])]).await;
        assert_eq!(ok, Ok(vec![1, 2, 3]));
    }

    #[tokio::test]
    async fn a_silent_upload_is_given_up_after_the_idle_timeout() {
        let idle = Duration::from_millis(200);
        let first = tokio_stream::iter(vec![head(3), data(vec![1])]);
        let mut s = first.chain(tokio_stream::pending());
        super::header(&mut s, "UploadRecords", idle).await.unwrap();
        let e = data_to_vec(&mut s, 3, idle).await.unwrap_err();
        assert!(matches!(e, UploadError::Idle(d) if d == idle), "{e:?}");
        assert_eq!(e.into_status().code(), tonic::Code::DeadlineExceeded);
    }
}
