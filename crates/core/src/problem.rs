//! A problem a component found in its own config section.
//!
//! Every component validates the section it owns and says what is wrong as a [`Problem`]: a
//! key path *relative to its section* (`fx`, `load.scale`, `tag[2].corners_mm`) and a message
//! saying what is wrong and what is expected. The component does not know where its section
//! sits in the file: the caller prefixes the path ([`Problem::within`]) and the binary's one
//! locator turns the whole path into `file:line: `key``.

use std::fmt;

/// A config problem: where (a dotted key path, `[i]` for array elements) and what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    /// Dotted key path, e.g. `camera[1].name`; empty for the section itself.
    pub key: String,
    /// What is wrong and what is expected.
    pub message: String,
}

impl Problem {
    /// A problem at `key` (relative to the section that reports it).
    pub fn new(key: impl Into<String>, message: impl Into<String>) -> Self {
        Self { key: key.into(), message: message.into() }
    }

    /// The same problem seen from the enclosing table: `prefix.key`.
    pub fn within(self, prefix: &str) -> Self {
        let key = match (prefix.is_empty(), self.key.is_empty()) {
            (true, _) => self.key,
            (false, true) => prefix.to_string(),
            (false, false) => format!("{prefix}.{}", self.key),
        };
        Self { key, message: self.message }
    }
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key.is_empty() {
            write!(f, "{}", self.message)
        } else {
            write!(f, "`{}`: {}", self.key, self.message)
        }
    }
}

impl std::error::Error for Problem {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn within_prefixes_the_path() {
        assert_eq!(Problem::new("fx", "m").within("camera[1]").key, "camera[1].fx");
        assert_eq!(Problem::new("", "m").within("utm").key, "utm");
        assert_eq!(Problem::new("a", "m").within("").key, "a");
    }
}
