//! Output files that are checked before the work and never leave anything
//! half-written behind: not on an error, not on Ctrl-C (SIGINT, SIGTERM,
//! SIGHUP), and, where the file system allows, not even on SIGKILL.
//!
//! [`OutputFile::create`] validates the destination (not a directory, not a
//! special file, its parent a directory, created if missing) and opens the
//! temporary that will hold the bytes in the destination's directory: an
//! anonymous `O_TMPFILE` where the file system supports it, which has no name
//! and so vanishes with the process however it dies, else an exclusively
//! created, uniquely named hidden file (`.NAME.pathfarm-PID-N`), removed on
//! drop and, by a signal handler, on SIGINT, SIGTERM and SIGHUP.
//!
//! [`commit_all`] writes and syncs every temporary of a group first and only
//! then moves each into place, so an output that fails to write leaves none
//! of the group behind. A destination that does not exist is created with
//! `linkat`, which never replaces a file (should one appear meanwhile, the
//! destination's check runs again); one that exists is replaced with `rename`
//! from a uniquely named hidden link. The moves run with termination signals
//! deferred, so Ctrl-C cannot stop a group half-way.
//!
//! The signal handler is async-signal-safe: it touches only atomics, calls
//! `unlink`/`rmdir` on paths from a fixed static table of C strings built
//! beforehand, and re-raises the signal with its default disposition (so the
//! exit status still says which signal ended the process). It is installed
//! only for signals whose disposition is the default (an ignored SIGINT, as
//! under `nohup` or `&`, stays ignored).

use std::ffi::{CString, OsString};
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::fd::AsRawFd;
use std::os::unix::ffi::{OsStrExt, OsStringExt};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::ptr::null_mut;
use std::sync::atomic::{AtomicI32, AtomicPtr, AtomicU32, AtomicUsize, Ordering::SeqCst};
use std::sync::Once;

use anyhow::{anyhow, bail, Result};

/// Decides whether an existing destination may be replaced (an error says why not).
type Check = Box<dyn Fn(&Path) -> Result<()>>;

/// An output, validated and with its temporary open, waiting for its bytes.
pub struct OutputFile {
    dest: PathBuf,
    dir: PathBuf,
    file: File,
    /// The temporary's name, if it has one: from the start for the named fallback,
    /// from commit on (only while it replaces an existing file) for an anonymous one.
    named: Option<Registered>,
    /// Whether the temporary is an `O_TMPFILE`, linkable through `/proc/self/fd`.
    anonymous: bool,
    check: Option<Check>,
    /// Parent directories this output created, outermost first; removed (if still
    /// empty) unless the output was committed.
    created_dirs: Vec<Registered>,
    committed: bool,
}

/// A path that the signal handler removes, and its slot in the handler's table.
struct Registered {
    path: PathBuf,
    slot: Option<usize>,
}

impl OutputFile {
    /// Opens `dest` for writing at the end; an existing regular file there will be replaced.
    pub fn create(dest: &Path) -> Result<Self> {
        Self::open(dest, None)
    }

    /// Like [`OutputFile::create`], but an existing `dest` is replaced only if `check`
    /// accepts it; `check` runs now and again just before the replacement.
    pub fn create_checked(
        dest: &Path,
        check: impl Fn(&Path) -> Result<()> + 'static,
    ) -> Result<Self> {
        Self::open(dest, Some(Box::new(check)))
    }

    pub fn path(&self) -> &Path {
        &self.dest
    }

    /// Writes `bytes`, syncs them and moves them into place.
    pub fn commit(self, bytes: &[u8]) -> Result<()> {
        commit_all(vec![(self, bytes)])
    }

    fn open(dest: &Path, check: Option<Check>) -> Result<Self> {
        install_signal_handlers();
        let show = dest.display();
        check_destination(dest, check.as_ref())?;
        let name = match dest.file_name() {
            Some(n) if !dest.as_os_str().as_bytes().ends_with(b"/") => n.to_os_string(),
            _ => bail!("cannot write {show}: not a file name"),
        };
        let dir = match dest.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let created_dirs = create_parents(dest, &dir)?;
        let (file, named, anonymous) = match open_anonymous(&dir) {
            Ok(Some(f)) => (f, None, true),
            Ok(None) => match open_named(&dir, &name) {
                Ok((f, reg)) => (f, Some(reg), false),
                Err(e) => {
                    remove_dirs(created_dirs, true);
                    bail!("cannot write {show}: creating a temporary: {e}");
                }
            },
            Err(e) => {
                remove_dirs(created_dirs, true);
                bail!("cannot write {show}: {e}");
            }
        };
        Ok(OutputFile {
            dest: dest.to_path_buf(),
            dir,
            file,
            named,
            anonymous,
            check,
            created_dirs,
            committed: false,
        })
    }

    /// Moves the written temporary to the destination.
    fn move_into_place(&mut self) -> io::Result<()> {
        let exists = std::fs::symlink_metadata(&self.dest).is_ok();
        if self.anonymous && !exists {
            // linkat never replaces: if a file appeared meanwhile, fall through to the
            // check-and-rename path.
            match link_fd(&self.file, &self.dest) {
                Ok(()) => return Ok(()),
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(e),
            }
        }
        if !self.anonymous && !exists {
            // A hard link does not replace either (where the file system has them).
            let tmp = &self.named.as_ref().expect("a named temporary").path;
            // On failure (a file appeared meanwhile, or no hard links here), check and
            // rename below.
            if std::fs::hard_link(tmp, &self.dest).is_ok() {
                let reg = self.named.take().expect("a named temporary");
                let _ = std::fs::remove_file(&reg.path);
                unregister(&FILES, reg.slot);
                return Ok(());
            }
        }
        check_destination(&self.dest, self.check.as_ref())
            .map_err(|e| io::Error::other(format!("{e:#}")))?;
        if self.anonymous && self.named.is_none() {
            self.named = Some(link_hidden(&self.file, &self.dir, &self.dest)?);
        }
        let tmp = &self.named.as_ref().expect("a named temporary").path;
        std::fs::rename(tmp, &self.dest)?;
        let reg = self.named.take().expect("a named temporary");
        unregister(&FILES, reg.slot);
        Ok(())
    }
}

impl Drop for OutputFile {
    fn drop(&mut self) {
        let _c = Critical::enter();
        if let Some(reg) = self.named.take() {
            if !self.committed {
                let _ = std::fs::remove_file(&reg.path);
            }
            unregister(&FILES, reg.slot);
        }
        remove_dirs(std::mem::take(&mut self.created_dirs), !self.committed);
    }
}

/// Unregisters directories that an output created, innermost first, removing them
/// (if empty) when `remove`.
fn remove_dirs(dirs: Vec<Registered>, remove: bool) {
    let _c = Critical::enter();
    for d in dirs.into_iter().rev() {
        if remove {
            let _ = std::fs::remove_dir(&d.path);
        }
        unregister(&DIRS, d.slot);
    }
}

/// Writes each output's bytes, then, once all are written and synced, moves them
/// all into place (in the given order). On an error before the moves nothing is left
/// behind; should a move fail after an earlier one succeeded, the message says which
/// outputs were written.
pub fn commit_all(outputs: Vec<(OutputFile, &[u8])>) -> Result<()> {
    let (mut files, bytes): (Vec<OutputFile>, Vec<&[u8]>) = outputs.into_iter().unzip();
    let result = commit_inner(&mut files, &bytes);
    // Last opened first, so a directory that several outputs share is removed last.
    while let Some(f) = files.pop() {
        drop(f);
    }
    result
}

fn commit_inner(files: &mut [OutputFile], bytes: &[&[u8]]) -> Result<()> {
    for (f, b) in files.iter_mut().zip(bytes) {
        f.file
            .write_all(b)
            .and_then(|_| f.file.sync_all())
            .map_err(|e| anyhow!("cannot write {}: {e}", f.dest.display()))?;
    }
    let _c = Critical::enter();
    for f in files.iter() {
        check_destination(&f.dest, f.check.as_ref())?;
    }
    for i in 0..files.len() {
        if let Err(e) = files[i].move_into_place() {
            let failed = files[i].dest.display().to_string();
            if i == 0 {
                bail!("cannot write {failed}: {e}");
            }
            let done: Vec<String> = files[..i]
                .iter()
                .map(|f| f.dest.display().to_string())
                .collect();
            bail!(
                "cannot write {failed}: {e}; {} was written already and is not from the same \
                 run as {failed} (run again to write both)",
                done.join(" and ")
            );
        }
        files[i].committed = true;
    }
    let mut synced: Vec<&Path> = Vec::new();
    for f in files.iter() {
        if !synced.contains(&f.dir.as_path()) {
            if let Ok(d) = File::open(&f.dir) {
                let _ = d.sync_all();
            }
            synced.push(&f.dir);
        }
    }
    Ok(())
}

/// Whether `a` and `b` name the same output (lexically, or the same existing file).
pub fn same_destination(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    if let (Ok(x), Ok(y)) = (std::path::absolute(a), std::path::absolute(b)) {
        if x == y {
            return true;
        }
    }
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => false,
    }
}

/// Refuses a destination that is a directory, a special file, or under a file, and an
/// existing one that `check` refuses.
fn check_destination(dest: &Path, check: Option<&Check>) -> Result<()> {
    let show = dest.display();
    match std::fs::metadata(dest) {
        Ok(m) if m.is_dir() => bail!("cannot write {show}: it is a directory"),
        Ok(m) if !m.is_file() => bail!("cannot write {show}: it exists and is not a regular file"),
        Ok(_) => {
            if let Some(c) = check {
                c(dest)?;
            }
            Ok(())
        }
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(()),
        Err(e) if e.raw_os_error() == Some(libc::ENOTDIR) => match file_ancestor(dest) {
            Some(a) => bail!("cannot write {show}: {} is not a directory", a.display()),
            None => bail!("cannot write {show}: {e}"),
        },
        Err(e) => bail!("cannot write {show}: {e}"),
    }
}

/// The nearest existing ancestor of `path` if it is not a directory.
fn file_ancestor(path: &Path) -> Option<PathBuf> {
    let mut a = path.parent();
    while let Some(p) = a {
        if p.as_os_str().is_empty() {
            return None;
        }
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() => return None,
            Ok(_) => return Some(p.to_path_buf()),
            Err(_) => a = p.parent(),
        }
    }
    None
}

/// Creates the missing directories of `dir`, outermost first, registering each for
/// removal should the output not be committed.
fn create_parents(dest: &Path, dir: &Path) -> Result<Vec<Registered>> {
    let show = dest.display();
    let mut missing = Vec::new();
    let mut d = Some(dir);
    while let Some(p) = d.filter(|p| !p.as_os_str().is_empty()) {
        match std::fs::metadata(p) {
            Ok(m) if m.is_dir() => break,
            Ok(_) => bail!("cannot write {show}: {} is not a directory", p.display()),
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                missing.push(p.to_path_buf());
                d = p.parent();
            }
            Err(e) => bail!("cannot write {show}: {}: {e}", p.display()),
        }
    }
    let mut created: Vec<Registered> = Vec::new();
    for p in missing.into_iter().rev() {
        let _c = Critical::enter();
        match std::fs::create_dir(&p) {
            Ok(()) => {
                let slot = register(&DIRS, &p);
                created.push(Registered { path: p, slot });
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && p.is_dir() => {}
            Err(e) => {
                remove_dirs(created, true);
                bail!("cannot write {show}: creating {}: {e}", p.display());
            }
        }
    }
    Ok(created)
}

/// An anonymous `O_TMPFILE` in `dir`, or `None` where the file system (or kernel)
/// has none, `/proc/self/fd` is missing (it is needed to link the file), or the
/// environment sets `PATHFARM_NO_O_TMPFILE`.
fn open_anonymous(dir: &Path) -> io::Result<Option<File>> {
    // For tests of the named fallback on file systems that have O_TMPFILE.
    if std::env::var_os("PATHFARM_NO_O_TMPFILE").is_some() {
        return Ok(None);
    }
    match OpenOptions::new()
        .read(true)
        .write(true)
        .mode(0o666)
        .custom_flags(libc::O_TMPFILE)
        .open(dir)
    {
        Ok(f) => {
            let proc = format!("/proc/self/fd/{}", f.as_raw_fd());
            Ok(std::fs::symlink_metadata(proc).is_ok().then_some(f))
        }
        Err(e)
            if matches!(
                e.raw_os_error(),
                Some(libc::EOPNOTSUPP | libc::EISDIR | libc::EINVAL)
            ) =>
        {
            Ok(None)
        }
        Err(e) => Err(e),
    }
}

static UNIQUE: AtomicU32 = AtomicU32::new(0);

/// `.NAME.pathfarm-PID-N` in `dir` (NAME cut so the whole stays a valid file name).
fn hidden_name(dir: &Path, name: &[u8]) -> PathBuf {
    let cut = &name[..name.len().min(200)];
    let mut s = OsString::from(".");
    s.push(OsString::from_vec(cut.to_vec()));
    s.push(format!(
        ".pathfarm-{}-{}",
        std::process::id(),
        UNIQUE.fetch_add(1, SeqCst)
    ));
    dir.join(s)
}

/// The named fallback: a new, exclusively created hidden file, registered for removal.
fn open_named(dir: &Path, name: &std::ffi::OsStr) -> io::Result<(File, Registered)> {
    loop {
        let path = hidden_name(dir, name.as_bytes());
        let _c = Critical::enter();
        match OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .mode(0o666)
            .open(&path)
        {
            Ok(f) => {
                let slot = register(&FILES, &path);
                return Ok((f, Registered { path, slot }));
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
}

fn c_path(p: &Path) -> io::Result<CString> {
    CString::new(p.as_os_str().as_bytes())
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidInput, "the path holds a NUL byte"))
}

/// Links the anonymous `file` at `dest`; fails with `AlreadyExists` if `dest` exists.
fn link_fd(file: &File, dest: &Path) -> io::Result<()> {
    let src = c_path(Path::new(&format!("/proc/self/fd/{}", file.as_raw_fd())))?;
    let dst = c_path(dest)?;
    // SAFETY: both are valid NUL-terminated strings that outlive the call.
    let r = unsafe {
        libc::linkat(
            libc::AT_FDCWD,
            src.as_ptr(),
            libc::AT_FDCWD,
            dst.as_ptr(),
            libc::AT_SYMLINK_FOLLOW,
        )
    };
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// Links the anonymous `file` at a new hidden name in `dir`, registered for removal.
/// Runs with termination signals deferred (from `commit_inner`).
fn link_hidden(file: &File, dir: &Path, dest: &Path) -> io::Result<Registered> {
    let name = dest.file_name().unwrap_or_default().as_bytes().to_vec();
    loop {
        let path = hidden_name(dir, &name);
        match link_fd(file, &path) {
            Ok(()) => {
                let slot = register(&FILES, &path);
                return Ok(Registered { path, slot });
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
}

// ---------------------------------------------------------------------------------------
// Signals

const SLOTS: usize = 32;
/// Files to unlink on a termination signal. The C strings are leaked on purpose:
/// a handler running on another thread may still be reading one when it is unregistered.
static FILES: [AtomicPtr<libc::c_char>; SLOTS] = [const { AtomicPtr::new(null_mut()) }; SLOTS];
/// Directories to remove (if empty) on a termination signal.
static DIRS: [AtomicPtr<libc::c_char>; SLOTS] = [const { AtomicPtr::new(null_mut()) }; SLOTS];
/// While above zero, a termination signal is only recorded in PENDING.
static CRITICAL: AtomicUsize = AtomicUsize::new(0);
static PENDING: AtomicI32 = AtomicI32::new(0);
const SIGNALS: [libc::c_int; 3] = [libc::SIGINT, libc::SIGTERM, libc::SIGHUP];

fn register(table: &[AtomicPtr<libc::c_char>; SLOTS], path: &Path) -> Option<usize> {
    // Relative paths stay valid: pathfarm never changes its working directory.
    let p = c_path(path).ok()?.into_raw();
    for (i, s) in table.iter().enumerate() {
        if s.compare_exchange(null_mut(), p, SeqCst, SeqCst).is_ok() {
            return Some(i);
        }
    }
    // SAFETY: `p` came from `into_raw` above and was never shared.
    drop(unsafe { CString::from_raw(p) });
    None
}

fn unregister(table: &[AtomicPtr<libc::c_char>; SLOTS], slot: Option<usize>) {
    if let Some(i) = slot {
        table[i].store(null_mut(), SeqCst);
    }
}

/// Removes every registered file, then every registered (empty) directory, innermost
/// first. Async-signal-safe: atomics, `unlink` and `rmdir` only.
fn remove_registered() {
    for s in FILES.iter() {
        let p = s.swap(null_mut(), SeqCst);
        if !p.is_null() {
            // SAFETY: registered pointers are leaked NUL-terminated strings.
            unsafe { libc::unlink(p) };
        }
    }
    // Directories were registered outermost first, but slots may be reused out of
    // order: retry until a pass removes nothing.
    for _ in 0..SLOTS {
        let mut progress = false;
        for s in DIRS.iter().rev() {
            let p = s.load(SeqCst);
            // SAFETY: as above.
            if !p.is_null() && unsafe { libc::rmdir(p) } == 0 {
                s.store(null_mut(), SeqCst);
                progress = true;
            }
        }
        if !progress {
            break;
        }
    }
}

/// Ends the process by `sig` with its default disposition. Async-signal-safe.
fn die(sig: libc::c_int) -> ! {
    // SAFETY: sigaction, sigprocmask and raise are async-signal-safe; the structures
    // are initialised before use.
    unsafe {
        let mut sa: libc::sigaction = std::mem::zeroed();
        sa.sa_sigaction = libc::SIG_DFL;
        libc::sigemptyset(&mut sa.sa_mask);
        libc::sigaction(sig, &sa, null_mut());
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, sig);
        libc::pthread_sigmask(libc::SIG_UNBLOCK, &set, null_mut());
        libc::raise(sig);
        libc::_exit(128 + sig)
    }
}

extern "C" fn on_signal(sig: libc::c_int) {
    PENDING.store(sig, SeqCst);
    // Re-checked after recording, so a critical section that ends meanwhile either
    // sees PENDING or leaves this handler to act: the swap hands the signal to one.
    if CRITICAL.load(SeqCst) == 0 {
        let sig = PENDING.swap(0, SeqCst);
        if sig != 0 {
            remove_registered();
            die(sig);
        }
    }
}

/// Defers termination signals while alive; acts on one that came meanwhile when the
/// last guard goes.
struct Critical;

impl Critical {
    fn enter() -> Self {
        CRITICAL.fetch_add(1, SeqCst);
        Critical
    }
}

impl Drop for Critical {
    fn drop(&mut self) {
        if CRITICAL.fetch_sub(1, SeqCst) == 1 {
            let sig = PENDING.swap(0, SeqCst);
            if sig != 0 {
                remove_registered();
                die(sig);
            }
        }
    }
}

fn install_signal_handlers() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        for sig in SIGNALS {
            // SAFETY: plain sigaction calls on zero-initialised structures; the handler
            // is async-signal-safe (see the module documentation).
            unsafe {
                let mut old: libc::sigaction = std::mem::zeroed();
                if libc::sigaction(sig, std::ptr::null(), &mut old) != 0
                    || old.sa_sigaction != libc::SIG_DFL
                {
                    continue;
                }
                let mut sa: libc::sigaction = std::mem::zeroed();
                sa.sa_sigaction = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
                sa.sa_flags = libc::SA_RESTART;
                libc::sigemptyset(&mut sa.sa_mask);
                for other in SIGNALS {
                    libc::sigaddset(&mut sa.sa_mask, other);
                }
                libc::sigaction(sig, &sa, null_mut());
            }
        }
    });
}
