use std::path::PathBuf;

/// Everything that can go wrong loading a scene. Every variant names the file
/// (and, where there is one, the line) at fault.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    #[error("{file}: cannot read: {source}")]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}:{line}: {message}")]
    Invalid {
        file: PathBuf,
        line: u32,
        message: String,
    },
}
