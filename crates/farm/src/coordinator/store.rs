//! The coordinator's content-addressed blob store: `DATA/blobs/<hex digest>`. Every blob is
//! written to a temporary file in `DATA/tmp` first and renamed into place only once its size
//! and digest are verified, so a half-written blob is never visible.

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::bundle::{digest_of, Digest};

/// Whether a blob is on disk when its put returns.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Durable {
    Now,
    /// Left to the kernel ([`BlobStore::sync`] waits for it).
    Later,
}

/// The blob directory and its temporary directory.
pub(crate) struct BlobStore {
    blobs: PathBuf,
    tmp: PathBuf,
    counter: AtomicU64,
}

impl BlobStore {
    /// Opens (creating) the store under `data`, emptying its temporary directory.
    pub(crate) fn open(data: &Path) -> io::Result<BlobStore> {
        let blobs = data.join("blobs");
        let tmp = data.join("tmp");
        fs::create_dir_all(&blobs)?;
        if tmp.exists() {
            fs::remove_dir_all(&tmp)?;
        }
        fs::create_dir_all(&tmp)?;
        Ok(BlobStore {
            blobs,
            tmp,
            counter: AtomicU64::new(0),
        })
    }

    pub(crate) fn path(&self, digest: &Digest) -> PathBuf {
        self.blobs.join(digest.to_hex())
    }

    pub(crate) fn has(&self, digest: &Digest) -> bool {
        self.path(digest).is_file()
    }

    /// [`BlobStore::has`], and if so restarts the blob's grace period (a client was told it
    /// is here and will count on it): see [`super::sweep`].
    pub(crate) fn has_and_touch(&self, digest: &Digest) -> bool {
        let Ok(f) = fs::File::options().append(true).open(self.path(digest)) else {
            return false;
        };
        let _ = f.set_modified(std::time::SystemTime::now());
        true
    }

    /// The size of a stored blob.
    pub(crate) fn size(&self, digest: &Digest) -> Option<u64> {
        fs::metadata(self.path(digest)).ok().map(|m| m.len())
    }

    /// How long ago the blob was written or touched.
    pub(crate) fn age(&self, digest: &Digest) -> Option<std::time::Duration> {
        let modified = fs::metadata(self.path(digest)).ok()?.modified().ok()?;
        Some(super::sweep::age_of(modified))
    }

    /// The stored blobs not written or touched within `grace`.
    pub(crate) fn older_than(&self, grace: std::time::Duration) -> Vec<Digest> {
        let Ok(dir) = fs::read_dir(&self.blobs) else {
            return Vec::new();
        };
        dir.filter_map(|e| {
            let e = e.ok()?;
            let digest = Digest::from_hex(e.file_name().to_str()?).ok()?;
            let modified = e.metadata().ok()?.modified().ok()?;
            (super::sweep::age_of(modified) >= grace).then_some(digest)
        })
        .collect()
    }

    /// Deletes a blob; true if it was there.
    pub(crate) fn remove(&self, digest: &Digest) -> bool {
        fs::remove_file(self.path(digest)).is_ok()
    }

    /// A fresh path in the temporary directory (not created).
    pub(crate) fn temp_path(&self, what: &str) -> PathBuf {
        let n = self.counter.fetch_add(1, Ordering::Relaxed);
        self.tmp.join(format!("{what}-{}-{n}", std::process::id()))
    }

    /// Stores `bytes` (if not already held) and returns their digest.
    pub(crate) fn put(&self, bytes: &[u8]) -> io::Result<Digest> {
        self.put_bytes(bytes, Durable::Now)
    }

    /// [`BlobStore::put`] of the bytes `write` hands its sink, piece by piece, hashed as they
    /// are written: a blob made on the fly never sits in memory whole (a checkpoint's film:
    /// 190 MB at 1920x1080).
    pub(crate) fn put_written(
        &self,
        write: impl FnOnce(&mut dyn FnMut(&[u8]) -> io::Result<()>) -> io::Result<()>,
    ) -> io::Result<Digest> {
        self.place(Durable::Now, |f| {
            let mut hasher = blake3::Hasher::new();
            write(&mut |piece: &[u8]| {
                hasher.update(piece);
                f.write_all(piece)
            })?;
            Ok(Digest(*hasher.finalize().as_bytes()))
        })
    }

    /// [`BlobStore::put`] without waiting for the disk: for blobs derived from state that is
    /// kept durably elsewhere (a unit's inputs), or made durable later ([`BlobStore::sync`]).
    pub(crate) fn put_unsynced(&self, bytes: &[u8]) -> io::Result<Digest> {
        self.put_bytes(bytes, Durable::Later)
    }

    fn put_bytes(&self, bytes: &[u8], durable: Durable) -> io::Result<Digest> {
        let digest = digest_of(bytes);
        if self.has(&digest) {
            return Ok(digest);
        }
        self.place(durable, |f| f.write_all(bytes).map(|()| digest))
    }

    /// Writes a temporary file with `write`, which returns the digest of what it wrote, and
    /// renames it into place as that blob (synced first with [`Durable::Now`]); a blob
    /// already held is kept and the file removed, as is the file on any error.
    fn place(
        &self,
        durable: Durable,
        write: impl FnOnce(&mut fs::File) -> io::Result<Digest>,
    ) -> io::Result<Digest> {
        let tmp = self.temp_path("blob");
        let result = (|| {
            let mut f = fs::File::create(&tmp)?;
            let digest = write(&mut f)?;
            if self.has(&digest) {
                fs::remove_file(&tmp)?;
                return Ok(digest);
            }
            if durable == Durable::Now {
                f.sync_all()?;
            }
            fs::rename(&tmp, self.path(&digest))?;
            Ok(digest)
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }

    /// Waits until the blob `d` is on disk.
    pub(crate) fn sync(&self, d: &Digest) -> io::Result<()> {
        fs::File::open(self.path(d))?.sync_all()
    }

    /// Starts an upload of a blob of `size` bytes with digest `digest`.
    pub(crate) fn begin(&self, digest: Digest, size: u64) -> io::Result<Upload> {
        let path = self.temp_path("upload");
        let file = fs::File::create(&path)?;
        Ok(Upload {
            digest,
            size,
            got: 0,
            hasher: blake3::Hasher::new(),
            file: Some(file),
            path,
            dest: self.path(&digest),
        })
    }
}

/// A blob being uploaded: its temporary file is removed unless [`Upload::finish`] succeeds.
pub(crate) struct Upload {
    digest: Digest,
    size: u64,
    got: u64,
    hasher: blake3::Hasher,
    file: Option<fs::File>,
    path: PathBuf,
    dest: PathBuf,
}

impl Upload {
    /// Appends a part. Fails (`Err(message)`) when the part would exceed the header's size.
    pub(crate) fn write(&mut self, data: &[u8]) -> Result<(), String> {
        self.got += data.len() as u64;
        if self.got > self.size {
            return Err(format!(
                "the blob's data exceeds the header's size of {} bytes",
                self.size
            ));
        }
        self.hasher.update(data);
        let file = self.file.as_mut().expect("open until finished");
        file.write_all(data)
            .map_err(|e| format!("cannot write the blob: {e}"))
    }

    /// Verifies size and digest and moves the blob into place.
    pub(crate) fn finish(mut self) -> Result<(), String> {
        if self.got != self.size {
            return Err(format!(
                "the blob's data is {} bytes, the header says {}",
                self.got, self.size
            ));
        }
        let got = Digest(*self.hasher.finalize().as_bytes());
        if got != self.digest {
            return Err(format!(
                "the blob's data has digest {}, the header says {}",
                got.to_hex(),
                self.digest.to_hex()
            ));
        }
        let file = self.file.take().expect("open until finished");
        file.sync_all()
            .map_err(|e| format!("cannot write the blob: {e}"))?;
        drop(file);
        fs::rename(&self.path, &self.dest).map_err(|e| format!("cannot store the blob: {e}"))
    }
}

impl Drop for Upload {
    fn drop(&mut self) {
        self.file.take();
        let _ = fs::remove_file(&self.path);
    }
}
