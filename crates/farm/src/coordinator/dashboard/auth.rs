//! The dashboard's sign-in: the API token, typed once into a form, buys an opaque session
//! cookie (`HttpOnly`, `SameSite=Strict`), so the token is never kept by the browser and a
//! script on the page cannot read the session. Each session has its own anti-forgery token,
//! which every action (a POST) must carry in its form besides the cookie. A second token,
//! the viewer's (`--viewer-token`), signs in a session that may look but not act.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The session cookie's name.
pub(super) const COOKIE: &str = "pathfarm_session";

/// Sessions kept at once: beyond it, the one closest to expiry goes (a flood of sign-ins
/// costs the flooder's sessions, bounded memory).
const MAX_SESSIONS: usize = 256;

/// How long a session lasts after its sign-in.
pub(super) const LIFETIME: Duration = Duration::from_secs(12 * 3600);

/// What a session may do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Role {
    /// Signed in with the API token: look and act (cancel, change priorities).
    Operator,
    /// Signed in with the viewer token: look only.
    Viewer,
}

/// A signed-in browser.
#[derive(Clone, Debug)]
pub(super) struct Session {
    /// The anti-forgery token its forms carry (hex).
    pub(super) csrf: String,
    pub(super) role: Role,
    expires: Instant,
}

/// The coordinator's tokens and the sessions they bought.
pub(super) struct Sessions {
    token: blake3::Hash,
    viewer: Option<blake3::Hash>,
    map: Mutex<HashMap<String, Session>>,
}

impl Sessions {
    /// Sessions signed in with `token` (operators) or `viewer` (viewers; none if `None`).
    pub(super) fn new(token: &str, viewer: Option<&str>) -> Self {
        Self {
            token: blake3::hash(token.as_bytes()),
            viewer: viewer.map(|v| blake3::hash(v.as_bytes())),
            map: Mutex::new(HashMap::new()),
        }
    }

    /// A new session's cookie value if `token` is the coordinator's or the viewer's
    /// (compared in constant time: `blake3::Hash` equality is), else `None`.
    pub(super) fn sign_in(&self, token: &str, now: Instant) -> Option<String> {
        let hash = blake3::hash(token.as_bytes());
        let role = match (hash == self.token, Some(hash) == self.viewer) {
            (true, _) => Role::Operator,
            (false, true) => Role::Viewer,
            (false, false) => return None,
        };
        let id = random_hex();
        let session = Session {
            csrf: random_hex(),
            role,
            expires: now + LIFETIME,
        };
        let mut map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        map.retain(|_, s| s.expires > now);
        if map.len() >= MAX_SESSIONS {
            let oldest = (map.iter())
                .min_by_key(|(_, s)| s.expires)
                .map(|(k, _)| k.clone());
            map.remove(&oldest.expect("the map is full"));
        }
        map.insert(id.clone(), session);
        Some(id)
    }

    /// The live session the request's `Cookie` header names, if any.
    pub(super) fn session(&self, cookie_header: Option<&str>, now: Instant) -> Option<Session> {
        let id = cookie_value(cookie_header?, COOKIE)?;
        let map = self.map.lock().unwrap_or_else(|e| e.into_inner());
        map.get(id).filter(|s| s.expires > now).cloned()
    }

    /// Ends the session the header names.
    pub(super) fn sign_out(&self, cookie_header: Option<&str>) {
        if let Some(id) = cookie_header.and_then(|h| cookie_value(h, COOKIE)) {
            let mut map = self.map.lock().unwrap_or_else(|e| e.into_inner());
            map.remove(id);
        }
    }
}

/// The value of cookie `name` in a `Cookie` header.
fn cookie_value<'a>(header: &'a str, name: &str) -> Option<&'a str> {
    (header.split(';'))
        .filter_map(|kv| kv.trim().split_once('='))
        .find(|(k, _)| *k == name)
        .map(|(_, v)| v)
}

/// 32 random bytes from the operating system, as hex.
fn random_hex() -> String {
    let mut b = [0u8; 32];
    getrandom::fill(&mut b).expect("the operating system's random numbers");
    b.iter().map(|x| format!("{x:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_token_signs_in_and_a_session_ends_at_its_lifetime_or_sign_out() {
        let s = Sessions::new("secret", Some("look"));
        let t0 = Instant::now();
        assert!(s.sign_in("wrong", t0).is_none());
        assert!(s.sign_in("", t0).is_none());
        let id = s.sign_in("secret", t0).expect("the token signs in");
        let header = format!("other=1; {COOKIE}={id}");
        let session = s.session(Some(&header), t0).expect("a live session");
        assert_eq!(session.csrf.len(), 64);
        assert_eq!(session.role, Role::Operator);
        let viewer = s.sign_in("look", t0).expect("the viewer token signs in");
        let viewer = s.session(Some(&format!("{COOKIE}={viewer}")), t0).unwrap();
        assert_eq!(viewer.role, Role::Viewer);
        let no_viewers = Sessions::new("secret", None);
        assert!(no_viewers.sign_in("look", t0).is_none());
        assert!(s.session(Some("pathfarm_session=forged"), t0).is_none());
        assert!(s.session(Some(&header), t0 + LIFETIME).is_none(), "expired");
        s.sign_out(Some(&header));
        assert!(s.session(Some(&header), t0).is_none(), "signed out");
    }

    #[test]
    fn sessions_are_bounded_and_the_oldest_go_first() {
        let s = Sessions::new("t", None);
        let t0 = Instant::now();
        let first = s.sign_in("t", t0).unwrap();
        for i in 1..=MAX_SESSIONS {
            s.sign_in("t", t0 + Duration::from_millis(i as u64))
                .unwrap();
        }
        assert_eq!(s.map.lock().unwrap().len(), MAX_SESSIONS);
        let gone = format!("{COOKIE}={first}");
        assert!(s.session(Some(&gone), t0).is_none());
    }
}
