//! Flags and output shared by the survey examples (`mod common;` in each). Each survey uses a
//! subset of these.
#![allow(dead_code)]

use std::fmt::Display;

/// Parses a seed list: `4`, `0-5` (inclusive), or a comma-separated mix such as `0-2,7,9`.
pub fn parse_seeds(text: &str) -> Result<Vec<u64>, String> {
    let mut seeds = Vec::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((lo, hi)) => {
                let lo: u64 = lo.trim().parse().map_err(|e| format!("`{part}`: {e}"))?;
                let hi: u64 = hi.trim().parse().map_err(|e| format!("`{part}`: {e}"))?;
                if hi < lo {
                    return Err(format!("`{part}`: the range is empty"));
                }
                seeds.extend(lo..=hi);
            }
            None => seeds.push(part.parse().map_err(|e| format!("`{part}`: {e}"))?),
        }
    }
    if seeds.is_empty() {
        return Err("no seeds given".into());
    }
    Ok(seeds)
}

/// A Markdown table printed to stdout, so a survey's output pastes into the docs as it is.
pub struct Table {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Table {
    /// A table with these column headings.
    pub fn new<S: Display>(header: &[S]) -> Self {
        Self {
            header: header.iter().map(ToString::to_string).collect(),
            rows: Vec::new(),
        }
    }

    /// Appends a row; it must have one cell per column.
    pub fn row<S: Display>(&mut self, cells: &[S]) {
        assert_eq!(cells.len(), self.header.len(), "one cell per column");
        self.rows
            .push(cells.iter().map(ToString::to_string).collect());
    }

    /// Prints the table as Markdown.
    pub fn print(&self) {
        let line = |cells: &[String]| println!("| {} |", cells.join(" | "));
        line(&self.header);
        println!("|{}", " --- |".repeat(self.header.len()));
        for r in &self.rows {
            line(r);
        }
    }
}

/// Arithmetic mean; NaN for an empty slice.
pub fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}
