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

/// At most the first `max_chars` characters of `text` (then `...`): input echoed in a
/// message, bounded.
pub fn shown_bounded(text: &str, max_chars: usize) -> String {
    match text.char_indices().nth(max_chars) {
        Some((i, _)) => format!("{}...", &text[..i]),
        None => text.to_string(),
    }
}
