//! The `--config` arguments that take JSON (embedding, fitting and training options): a file,
//! or the JSON object itself written inline, so a command from docs/RESULTS.md such as
//! `bench quality --config '{"finetune":{"steps":600}}'` runs as written.

use anyhow::{Context, Result};
use serde::de::DeserializeOwned;
use std::path::Path;

/// The options a JSON `--config` argument holds ([`json_config`]), parsed; `what` names them in
/// the error ("embedding options": "X is not valid embedding options: …").
pub(crate) fn read_json_config<T: DeserializeOwned>(arg: &Path, what: &str) -> Result<T> {
    let bytes = json_config(arg)?;
    serde_json::from_slice(&bytes).with_context(|| format!("{} is not valid {what}", arg.display()))
}

/// The JSON bytes of a `--config` argument: the argument itself when it is a JSON object
/// written inline (it starts with `{`, which no options file written by splatmark is named
/// with), else the contents of the file it names.
fn json_config(arg: &Path) -> Result<Vec<u8>> {
    if let Some(s) = arg.to_str()
        && s.trim_start().starts_with('{')
    {
        return Ok(s.as_bytes().to_vec());
    }
    std::fs::read(arg).with_context(|| format!("cannot read {}", arg.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_config_is_read_inline_or_from_its_file_and_a_missing_file_says_so() {
        let inline = r#" {"finetune":{"steps":600}}"#;
        assert_eq!(json_config(Path::new(inline)).unwrap(), inline.as_bytes());
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("c.json");
        std::fs::write(&file, br#"{"seed":3}"#).unwrap();
        assert_eq!(json_config(&file).unwrap(), br#"{"seed":3}"#);
        let missing = dir.path().join("missing.json");
        let e = json_config(&missing).unwrap_err().to_string();
        assert!(
            e.starts_with("cannot read ") && e.contains("missing.json"),
            "{e}"
        );
    }
}
