//! Reading input files safely: regular files only, never more than a cap.
//!
//! Every loader in the crate (measured matrices, Gaussian-mixture fits, spectra and
//! lamp CSVs, coefficient cubes, material JSON) reads through [`read_bytes`] or
//! [`read_text`]. They refuse anything that is not a regular file *before opening it*
//! (opening a FIFO blocks until a writer appears; `/dev/zero` never ends), refuse a
//! file whose length exceeds the cap for its kind, and read through `take(cap + 1)`
//! so that a file growing while it is read (or metadata that lies) still cannot make
//! the read unbounded. Callers then check every size a header claims against the
//! bytes actually read before allocating for it.

use std::io::Read;
use std::path::Path;

use crate::{Error, Result};

/// Cap for a measured reradiation matrix (`.bfc`, `.csv`, `.exr`): the shipped and
/// shared files are 24 kB; a 1 nm × 1 nm matrix over 300–1000 nm in CSV is ~5 MB.
pub const MAX_MATRIX_FILE_BYTES: u64 = 64 << 20;
/// Cap for a Gaussian-mixture fit (`.gmm.json`), a material JSON or a lamp/spectrum CSV.
pub const MAX_SMALL_FILE_BYTES: u64 = 16 << 20;
/// Cap for a coefficient cube (the largest accepted resolution, 129³ × 5 f32, is 43 MB).
pub const MAX_CUBE_FILE_BYTES: u64 = 64 << 20;

/// The bytes of the regular file `path`, at most `cap` of them. `what` names the kind
/// of file in errors (e.g. `"reradiation matrix"`).
pub fn read_bytes(path: &Path, cap: u64, what: &str) -> Result<Vec<u8>> {
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| Error::Io(format!("{shown}: cannot read {what}: {e}")))?;
    if !meta.is_file() {
        let kind = if meta.is_dir() { "a directory" } else { "not a regular file (a FIFO, socket or device)" };
        return Err(Error::Io(format!("{shown}: {kind}; a {what} must be a regular file")));
    }
    let too_large = |n: u64| {
        Error::Io(format!("{shown}: {what} of {n} bytes or more; at most {cap} bytes are read ({} MiB)", cap >> 20))
    };
    if meta.len() > cap {
        return Err(too_large(meta.len()));
    }
    let file = std::fs::File::open(path).map_err(|e| Error::Io(format!("{shown}: cannot read {what}: {e}")))?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(cap + 1).read_to_end(&mut bytes).map_err(|e| Error::Io(format!("{shown}: cannot read {what}: {e}")))?;
    if bytes.len() as u64 > cap {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// [`read_bytes`] as UTF-8 text.
pub fn read_text(path: &Path, cap: u64, what: &str) -> Result<String> {
    let bytes = read_bytes(path, cap, what)?;
    String::from_utf8(bytes).map_err(|e| {
        Error::data(format!(
            "{}: {what} is not UTF-8 text (invalid byte at offset {})",
            path.display(),
            e.utf8_error().valid_up_to()
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_devices_directories_and_oversized_files() {
        let e = read_bytes(Path::new("/dev/zero"), 1024, "lamp CSV").unwrap_err().to_string();
        assert!(e.contains("/dev/zero") && e.contains("not a regular file"), "{e}");
        let e = read_bytes(Path::new("/tmp"), 1024, "lamp CSV").unwrap_err().to_string();
        assert!(e.contains("a directory"), "{e}");
        let dir = std::env::temp_dir().join(format!("fluo-fileio-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let big = dir.join("big.csv");
        std::fs::write(&big, vec![b'1'; 4096]).unwrap();
        let e = read_bytes(&big, 1024, "lamp CSV").unwrap_err().to_string();
        assert!(e.contains("4096 bytes") && e.contains("at most 1024"), "{e}");
        assert_eq!(read_bytes(&big, 4096, "lamp CSV").unwrap().len(), 4096);
        let e = read_bytes(&dir.join("missing.csv"), 1024, "lamp CSV").unwrap_err().to_string();
        assert!(e.contains("missing.csv") && e.contains("cannot read lamp CSV"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[cfg(unix)]
    #[test]
    fn refuses_a_fifo_without_blocking() {
        let dir = std::env::temp_dir().join(format!("fluo-fifo-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let fifo = dir.join("pipe.bfc");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let e = read_text(&fifo, 1024, "reradiation matrix").unwrap_err().to_string();
        assert!(e.contains("not a regular file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
