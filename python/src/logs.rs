//! `read_log` and `summary`: the table `inspect --csv` writes, and `inspect`'s statistics of
//! such a table, from the same code as the command.

use crate::errors::IntoPy;
use crate::wait::{self, OnInterrupt};
use pyo3::prelude::*;
use pyo3::types::{PyList, PyString};
use serde_json::Value;
use std::path::PathBuf;
use sunjitter_core::{Error, Result};
use sunjitter_io::sink::ReferenceChange;
use sunjitter_runtime::inspect::{self, csv, InspectOptions, LogSummary};

/// A JSON value as the Python object `json.loads` would give.
fn value_to_py<'py>(py: Python<'py>, v: &Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match v {
        Value::Null => py.None().into_bound(py),
        Value::Bool(b) => b.into_pyobject(py)?.to_owned().into_any(),
        Value::Number(n) => match (n.as_i64(), n.as_u64()) {
            (Some(i), _) => i.into_pyobject(py)?.into_any(),
            (None, Some(u)) => u.into_pyobject(py)?.into_any(),
            _ => n.as_f64().unwrap_or(f64::NAN).into_pyobject(py)?.into_any(),
        },
        Value::String(s) => PyString::new(py, s).into_any(),
        other => PyString::new(py, &other.to_string()).into_any(),
    })
}

/// [`read_log`]'s answer: column names, each column's cells, the files read, the `/log` tally,
/// the `/reference` messages.
type LogTable<'py> = (Vec<String>, Bound<'py, PyList>, Vec<String>, String, String);

/// The logs' table, column by column: `(columns, values, files, log, references)`, where
/// `values[i]` is column i's cells, `files` the MCAP files read (in order), `log` the `/log`
/// tally (JSON) and `references` the `/reference` messages (JSON: their keyframe closures).
#[pyfunction]
pub fn read_log<'py>(py: Python<'py>, paths: Vec<PathBuf>) -> PyResult<LogTable<'py>> {
    let work = move || -> Result<(csv::Table, Vec<String>, String, String)> {
        let files = inspect::log_files(&paths)?;
        let (frames, references, log) = inspect::read_frames_and_references(&files)?;
        let analyses = inspect::analyse(&frames, &InspectOptions::default());
        let table = csv::table(&analyses)
            .map_err(|e| Error::Usage(format!("cannot tabulate the log: {e}")))?;
        let names = files.iter().map(|p| p.display().to_string()).collect();
        let log = serde_json::to_string(&log)
            .map_err(|e| Error::Usage(format!("cannot encode the /log tally: {e}")))?;
        let references = serde_json::to_string(&references)
            .map_err(|e| Error::Usage(format!("cannot encode the /reference messages: {e}")))?;
        Ok((table, names, log, references))
    };
    let (table, files, log, references) =
        wait::run(py, "read_log", work, OnInterrupt::Abandon, |_| Ok(()))?.py_err()?;
    let columns = PyList::empty(py);
    for i in 0..table.columns.len() {
        let cells = PyList::empty(py);
        for row in &table.rows {
            cells.append(value_to_py(py, &row[i])?)?;
        }
        columns.append(cells)?;
    }
    Ok((table.columns, columns, files, log, references))
}

/// A Python cell as JSON: None, bool, int, float (NaN: null) or str.
fn cell_from_py(cell: &Bound<'_, PyAny>) -> PyResult<Value> {
    if cell.is_none() {
        return Ok(Value::Null);
    }
    if let Ok(b) = cell.cast::<pyo3::types::PyBool>() {
        return Ok(Value::Bool(b.is_true()));
    }
    if let Ok(i) = cell.extract::<i64>() {
        if cell.is_instance_of::<pyo3::types::PyInt>() {
            return Ok(Value::from(i));
        }
    }
    if let Ok(s) = cell.extract::<String>() {
        return Ok(Value::String(s));
    }
    let f: f64 = cell.extract()?;
    Ok(serde_json::Number::from_f64(f).map_or(Value::Null, Value::Number))
}

/// `inspect --json`'s document for a table: `columns` and their cells (as [`read_log`] gives
/// them; `obs_time` as ns since the epoch or None), the files and `/log` tally to report.
#[pyfunction]
pub fn summary(
    py: Python<'_>,
    columns: Vec<String>,
    values: Vec<Bound<'_, PyList>>,
    files: Vec<String>,
    log: Option<String>,
    references: Option<String>,
) -> PyResult<String> {
    if values.len() != columns.len() {
        return Err(pyo3::exceptions::PyValueError::new_err(
            "one list of cells per column",
        ));
    }
    let rows = values.first().map_or(0, |c| c.len());
    let obs_time = columns.iter().position(|c| c == "obs_time");
    let mut table = vec![Vec::with_capacity(columns.len()); rows];
    for (i, cells) in values.iter().enumerate() {
        if cells.len() != rows {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "every column has one cell per row",
            ));
        }
        for (row, cell) in table.iter_mut().zip(cells.iter()) {
            let mut value = cell_from_py(&cell)?;
            if Some(i) == obs_time {
                value = match value.as_i64() {
                    Some(ns) => Value::String(sunjitter_core::time::format_iso_utc(ns)),
                    None => Value::String(String::new()),
                };
            }
            row.push(value);
        }
    }
    let frames = table
        .into_iter()
        .enumerate()
        .map(|(i, row)| {
            csv::frame_from_row(&columns, row)
                .map_err(|e| Error::Usage(format!("row {i} is not a logged frame: {e}")))
        })
        .collect::<Result<Vec<_>>>()
        .py_err()?;
    let log: LogSummary = match log {
        Some(text) => serde_json::from_str(&text)
            .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?,
        None => LogSummary::default(),
    };
    let references: Vec<ReferenceChange> = match references {
        Some(text) => serde_json::from_str(&text)
            .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))?,
        None => Vec::new(),
    };
    wait::detached(py, "summary", move || {
        let analyses = inspect::analyse(&frames, &InspectOptions::default());
        let mut report = inspect::report(&files, &analyses, log);
        report.consistency = inspect::consistency::consistency(&frames, &references);
        serde_json::to_string(&report)
    })?
    .map_err(|e| pyo3::exceptions::PyValueError::new_err(e.to_string()))
}
