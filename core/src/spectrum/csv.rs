//! A minimal reader for the small numeric CSV tables used here.
//!
//! Rules: blank lines and lines whose first non-blank character is `#` are skipped;
//! fields are separated by commas, semicolons or whitespace and trimmed; the first
//! remaining line may be a header (it is skipped when none of its fields is a number);
//! every other line must have exactly the expected number of fields.

use crate::{Error, Result};

/// Data lines of `text` as `(1-based line number, fields)`, comments, blank lines and a
/// leading header removed.
fn rows(text: &str) -> impl Iterator<Item = (usize, Vec<&str>)> {
    let mut first = true;
    text.lines()
        .enumerate()
        .filter_map(|(i, line)| {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                return None;
            }
            let fields: Vec<&str> = if line.contains([',', ';']) {
                line.split([',', ';']).map(str::trim).collect()
            } else {
                line.split_whitespace().collect()
            };
            Some((i + 1, fields))
        })
        .filter(move |(_, fields)| {
            let is_header = first && fields.iter().all(|f| f.parse::<f64>().is_err());
            first = false;
            !is_header
        })
}

/// Parse one numeric field, with an error naming the line and the field.
fn number(line: usize, field: &str) -> Result<f64> {
    field.parse::<f64>().map_err(|_| Error::data(format!("line {line}: cannot read \"{field}\" as a number")))
}

/// The fields of a data line, checking that there are exactly `n`.
fn expect_fields<'a>(line: usize, fields: &'a [&'a str], n: usize) -> Result<&'a [&'a str]> {
    if fields.len() == n {
        Ok(fields)
    } else {
        Err(Error::data(format!("line {line}: expected {n} columns, found {}", fields.len())))
    }
}

/// Read an `nm,value` table into its two columns.
pub(super) fn two_columns(text: &str) -> Result<(Vec<f64>, Vec<f64>)> {
    let mut wavelengths = Vec::new();
    let mut values = Vec::new();
    for (line, fields) in rows(text) {
        let f = expect_fields(line, &fields, 2)?;
        wavelengths.push(number(line, f[0])?);
        values.push(number(line, f[1])?);
    }
    if wavelengths.len() < 2 {
        return Err(Error::data(format!(
            "found {} data row(s); a spectrum needs at least 2 rows of \"nm,value\"",
            wavelengths.len()
        )));
    }
    Ok((wavelengths, values))
}

/// Read an all-numeric table with `n` columns, returned column by column.
pub(super) fn columns(text: &str, n: usize) -> Result<Vec<Vec<f64>>> {
    let mut cols = vec![Vec::new(); n];
    for (line, fields) in rows(text) {
        let f = expect_fields(line, &fields, n)?;
        for (col, field) in cols.iter_mut().zip(f) {
            col.push(number(line, field)?);
        }
    }
    Ok(cols)
}

/// One named group of a long-format table: `(name, wavelengths_nm, values)`.
type NamedColumns = (String, Vec<f64>, Vec<f64>);

/// Read a long-format `name,nm,value` table into `(name, wavelengths, values)` groups,
/// in order of first appearance; the rows of one name must be contiguous.
pub(super) fn named_groups(text: &str) -> Result<Vec<NamedColumns>> {
    let mut groups: Vec<NamedColumns> = Vec::new();
    for (line, fields) in rows(text) {
        let f = expect_fields(line, &fields, 3)?;
        let (w, v) = (number(line, f[1])?, number(line, f[2])?);
        match groups.last_mut() {
            Some(g) if g.0 == f[0] => {
                g.1.push(w);
                g.2.push(v);
            }
            _ => {
                if groups.iter().any(|g| g.0 == f[0]) {
                    return Err(Error::data(format!("line {line}: rows of \"{}\" are not contiguous", f[0])));
                }
                groups.push((f[0].to_string(), vec![w], vec![v]));
            }
        }
    }
    Ok(groups)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn comments_header_and_separators() {
        let text = "# a comment\n\nnm,value\n380, 1.5\n385;2\n  390\t2.5  \n# end\n";
        let (w, v) = two_columns(text).unwrap();
        assert_eq!(w, vec![380.0, 385.0, 390.0]);
        assert_eq!(v, vec![1.5, 2.0, 2.5]);
        // Without a header.
        assert_eq!(two_columns("1 2\n3 4").unwrap().0, vec![1.0, 3.0]);
    }

    #[test]
    fn errors_name_the_line() {
        let e = two_columns("nm,value\n380,1\n385,abc\n").unwrap_err();
        assert!(e.to_string().contains("line 3") && e.to_string().contains("abc"), "{e}");
        let e = two_columns("380,1,2\n385,1\n").unwrap_err();
        assert!(e.to_string().contains("line 1") && e.to_string().contains("2 columns"), "{e}");
        // A second non-numeric line is not a header.
        let e = two_columns("nm,value\nx,y\n1,2\n").unwrap_err();
        assert!(e.to_string().contains("line 2"), "{e}");
        let e = two_columns("# only comments\n").unwrap_err();
        assert!(e.to_string().contains("at least 2"), "{e}");
        let e = named_groups("a,1,1\nb,1,1\na,2,2\n").unwrap_err();
        assert!(e.to_string().contains("contiguous"), "{e}");
    }
}
