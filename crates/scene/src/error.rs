use std::path::PathBuf;

/// Everything that can go wrong loading a scene. Every variant names the file
/// (and, where there is one, the line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The OS error is part of the message, not a `source`: error chains (anyhow's `{:#}`)
    /// would print it twice.
    #[error("{file}: cannot read: {error}")]
    Io {
        file: PathBuf,
        error: std::io::Error,
    },
    #[error("{file}:{line}: {message}")]
    Invalid {
        file: PathBuf,
        line: u32,
        message: String,
    },
}
