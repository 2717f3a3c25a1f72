//! The users of the control API (`[output] users_file`, docs/audit.md): each a name, a role
//! and the SHA-256 of their own bearer token (the token itself is printed once by
//! `tagdeflect user add` and kept nowhere).
//!
//! ```toml
//! [[user]]
//! name = "ana"
//! role = "operator"
//! token_sha256 = "9f86d0…"
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::audit::hex;

/// What a user may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Starts, stops, marks, zeroes, enters cracks and imports specimens.
    Operator,
    /// Signs reports and asks re-analyses.
    Reviewer,
    /// Everything, plus methods and users.
    Admin,
}

impl Role {
    /// The role's name as written (`operator`, `reviewer`, `admin`).
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Operator => "operator",
            Role::Reviewer => "reviewer",
            Role::Admin => "admin",
        }
    }

    /// The role an action of the control API needs besides `admin` (`None`: admin only).
    pub fn needed_for(action: &str) -> Option<Role> {
        match action {
            "start" | "stop" | "mark" | "zero" | "crack" | "specimens" => Some(Role::Operator),
            "sign" | "reanalyse" => Some(Role::Reviewer),
            _ => None,
        }
    }

    /// Whether this role may do `action`; else the words of the refusal (the role needed).
    pub fn may(self, action: &str) -> Result<(), String> {
        let needed = Role::needed_for(action);
        if self == Role::Admin || needed == Some(self) {
            return Ok(());
        }
        let needed = needed.map_or("admin".to_string(), |r| format!("{} or admin", r.as_str()));
        Err(format!("{action} needs the role {needed}; this token's role is {}", self.as_str()))
    }
}

/// Who did an action: a user's name and role.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Actor {
    /// The user's name (`shared-token` for the one shared token).
    pub user: String,
    /// Their role.
    pub role: Role,
}

impl Actor {
    /// The one shared token of a daemon without a users file: user `shared-token`, role `admin`.
    pub fn shared_token() -> Actor {
        Actor { user: "shared-token".into(), role: Role::Admin }
    }
}

/// One user of the users file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct User {
    /// Their name (letters, digits, `_`, `-`, `.`, `@`; at most 64).
    pub name: String,
    /// Their role.
    pub role: Role,
    /// SHA-256 (hex) of their bearer token.
    pub token_sha256: String,
}

/// The users file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Users {
    /// Its users (`[[user]]`).
    #[serde(default, rename = "user")]
    pub users: Vec<User>,
}

/// Why a users file cannot be taken.
#[derive(Debug, thiserror::Error)]
pub enum UsersError {
    /// It cannot be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The system's error.
        source: std::io::Error,
    },
    /// It is not a users file, or a user in it is not well formed.
    #[error("{path}: {message}")]
    Bad {
        /// The file.
        path: String,
        /// What is wrong, naming the user.
        message: String,
    },
}

/// Whether `name` is fit for a user's name.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty() && name.len() <= 64 && name.chars().all(|c| c.is_alphanumeric() || matches!(c, '_' | '-' | '.' | '@'))
}

/// SHA-256 (hex) of a bearer token.
pub fn token_sha256(token: &str) -> String {
    use sha2::Digest;
    hex(&sha2::Sha256::digest(token.as_bytes()))
}

/// Equal bytes, compared without an early exit.
pub fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl Users {
    /// Reads and checks the users file at `path` (a missing file is an error: a daemon told to
    /// use one must not start without it).
    pub fn read(path: &Path) -> Result<Users, UsersError> {
        let shown = path.display().to_string();
        let text = crate::text_file::read_text_limited(path).map_err(|source| UsersError::Io { path: shown.clone(), source })?;
        let users: Users = toml::from_str(&text).map_err(|e| UsersError::Bad { path: shown.clone(), message: e.to_string() })?;
        users.check().map_err(|message| UsersError::Bad { path: shown, message })?;
        Ok(users)
    }

    /// Names well formed and unique, hashes 64 hex digits and unique.
    pub fn check(&self) -> Result<(), String> {
        for (i, u) in self.users.iter().enumerate() {
            if !valid_name(&u.name) {
                return Err(format!("user[{i}] name \"{}\": 1 to 64 letters, digits, `_`, `-`, `.`, `@`", u.name.escape_debug()));
            }
            if u.token_sha256.len() != 64 || !u.token_sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
                return Err(format!("user \"{}\": token_sha256 must be 64 hex digits", u.name));
            }
            if self.users[..i].iter().any(|o| o.name == u.name) {
                return Err(format!("user \"{}\" is listed twice", u.name));
            }
            if self.users[..i].iter().any(|o| o.token_sha256.eq_ignore_ascii_case(&u.token_sha256)) {
                return Err(format!("user \"{}\" has the token of another user", u.name));
            }
        }
        Ok(())
    }

    /// The user whose token `given` is: the token hashed once and compared with every stored
    /// hash in constant time, without stopping at a match (the time does not tell which
    /// user, nor whether one matched early).
    pub fn find(&self, given: &str) -> Option<Actor> {
        let hash = token_sha256(given);
        let mut found: Option<usize> = None;
        for (i, u) in self.users.iter().enumerate() {
            let eq = constant_time_eq(hash.as_bytes(), u.token_sha256.to_ascii_lowercase().as_bytes());
            found = if eq { Some(i) } else { found };
        }
        found.map(|i| Actor { user: self.users[i].name.clone(), role: self.users[i].role })
    }

    /// The file's text.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("users serialise")
    }
}

/// Whose tokens the control API takes: the one shared token of a daemon without a users
/// file, or each user's own.
#[derive(Debug, Clone, PartialEq)]
pub enum Credentials {
    /// One token for everyone (user `shared-token`, role `admin`).
    Shared(String),
    /// The users of `[output] users_file`.
    Users(Users),
}

impl Credentials {
    /// Who holds the token `given`, if anyone (compared in constant time).
    pub fn find(&self, given: &str) -> Option<Actor> {
        match self {
            Credentials::Shared(token) => constant_time_eq(given.as_bytes(), token.as_bytes()).then(Actor::shared_token),
            Credentials::Users(users) => users.find(given),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_token_finds_its_user_and_roles_allow_their_actions() {
        let users = Users {
            users: vec![
                User { name: "ana".into(), role: Role::Operator, token_sha256: token_sha256("tok-ana") },
                User { name: "rui".into(), role: Role::Reviewer, token_sha256: token_sha256("tok-rui") },
            ],
        };
        users.check().unwrap();
        assert_eq!(users.find("tok-rui"), Some(Actor { user: "rui".into(), role: Role::Reviewer }));
        assert_eq!(users.find("tok-ana").unwrap().user, "ana");
        assert_eq!(users.find("tok-eve"), None);
        assert!(Role::Operator.may("start").is_ok() && Role::Reviewer.may("sign").is_ok() && Role::Admin.may("method").is_ok());
        assert_eq!(Role::Reviewer.may("start").unwrap_err(), "start needs the role operator or admin; this token's role is reviewer");
        assert_eq!(Role::Operator.may("sign").unwrap_err(), "sign needs the role reviewer or admin; this token's role is operator");
        assert!(Role::Operator.may("method").unwrap_err().contains("needs the role admin"));
        let back: Users = toml::from_str(&users.to_toml()).unwrap();
        assert_eq!(back, users);
        let twice = Users { users: vec![users.users[0].clone(), users.users[0].clone()] };
        assert!(twice.check().unwrap_err().contains("listed twice"));
    }
}
