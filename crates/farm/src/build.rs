//! The build identity workers and the coordinator compare: different builds may round
//! differently, and a job's bits must not depend on which worker took a tile.

use std::sync::OnceLock;

/// `pathfarm VERSION EXE-DIGEST`: the package version and the first 16 hex digits of the
/// blake3 digest of the running executable (computed once). A binary that cannot read its
/// own executable reports `unknown` as the digest, which matches no other build.
pub fn build_id() -> &'static str {
    static ID: OnceLock<String> = OnceLock::new();
    ID.get_or_init(|| {
        // Streamed, not read whole: the executable is about 100 MB with its debug info, and
        // every process (coordinator, each worker, each client) computes this at start-up.
        let digest = std::env::current_exe()
            .and_then(std::fs::File::open)
            .and_then(|f| blake3::Hasher::new().update_reader(f).map(|h| h.finalize()))
            .map(|h| h.to_hex()[..16].to_string())
            .unwrap_or_else(|_| "unknown".to_string());
        format!("pathfarm {} {digest}", env!("CARGO_PKG_VERSION"))
    })
}
