//! The configuration of a call: a TOML file (as `--config`), a table (a Python dict, passed as
//! JSON text), or the defaults.

use std::path::PathBuf;
use sunjitter_core::{Error, Result};
use sunjitter_runtime::config::{Config, Overrides};

/// Where the configuration comes from.
pub enum Source {
    Defaults,
    File(PathBuf),
    /// A table in JSON, the same keys and values as the TOML file.
    Table(String),
}

impl Source {
    pub fn new(path: Option<PathBuf>, table_json: Option<String>) -> Source {
        match (path, table_json) {
            (Some(path), _) => Source::File(path),
            (None, Some(json)) => Source::Table(json),
            (None, None) => Source::Defaults,
        }
    }

    /// The file the configuration is read from, which no output may overwrite.
    pub fn path(&self) -> Option<&std::path::Path> {
        match self {
            Source::File(path) => Some(path),
            _ => None,
        }
    }

    /// The configuration with `overrides`, checked as the command line checks it.
    pub fn load(&self, overrides: &Overrides) -> Result<Config> {
        let json = match self {
            Source::Defaults => return Config::load(None, overrides),
            Source::File(path) => return Config::load(Some(path), overrides),
            Source::Table(json) => json,
        };
        let bad = |e: String| Error::Usage(format!("configuration: {e}"));
        let table: toml::Value = serde_json::from_str(json).map_err(|e| bad(e.to_string()))?;
        let text = toml::to_string(&table).map_err(|e| bad(e.to_string()))?;
        let mut config = Config::from_toml(&text).map_err(bad)?;
        config.apply(overrides);
        config.validate()?;
        Ok(config)
    }
}
