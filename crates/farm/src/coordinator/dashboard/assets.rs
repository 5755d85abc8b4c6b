//! The dashboard's stylesheet and script, compiled into the binary: the page loads nothing
//! from anywhere but the coordinator (it works on an offline farm).

const CSS: &str = include_str!("assets/app.css");
const JS: &str = include_str!("assets/app.js");
const ICON: &str = include_str!("assets/icon.svg");

/// An asset's body and content type, by file name.
pub(super) fn get(name: &str) -> Option<(&'static str, &'static str)> {
    match name {
        "app.css" => Some((CSS, "text/css; charset=utf-8")),
        "app.js" => Some((JS, "text/javascript; charset=utf-8")),
        "icon.svg" => Some((ICON, "image/svg+xml")),
        _ => None,
    }
}

/// Every asset's bytes: the page's budget (`tests`).
#[cfg(test)]
pub(super) fn total_bytes() -> usize {
    CSS.len() + JS.len() + ICON.len()
}

#[cfg(test)]
mod tests {
    /// The page's own assets (images aside) stay within 200 KB uncompressed.
    #[test]
    fn the_assets_fit_their_budget() {
        assert!(
            super::total_bytes() <= 200 * 1024,
            "{} bytes",
            super::total_bytes()
        );
        assert!(super::get("app.css").is_some() && super::get("app.js").is_some());
        assert!(super::get("../mod.rs").is_none());
    }
}
