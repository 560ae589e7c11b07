//! Output files the tools write: each replaced atomically, so a run that is
//! stopped or fails midway leaves the previous file or the new one, never a
//! torn mix; and text printed to stdout.

use std::io::Write;
use std::path::Path;

use anyhow::{Context, Result};

/// Prints to stdout; a reader that closed the pipe early (`| head`) is not an error.
/// `--out` of a command that writes a local directory: a URL is refused (a path of
/// `s3://bucket/x` would be the local folder `./s3:/bucket/x`, and nothing would reach the
/// bucket).
pub fn local_out(text: &str) -> std::result::Result<std::path::PathBuf, String> {
    if citystream_dataset::looks_like_url(text) {
        return Err(format!(
            "{text} is a URL; this command writes a local directory (datasets go to S3 through \
             --shard I/N and `citystream merge`, docs/SHARDS.md)"
        ));
    }
    Ok(std::path::PathBuf::from(text))
}

pub fn print_stdout(text: &str) -> Result<()> {
    match std::io::stdout().lock().write_all(text.as_bytes()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        other => Ok(other?),
    }
}

/// Writes `bytes` to a temporary file beside `path`, syncs it and renames it
/// into place.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let temp = path.with_extension(format!("tmp-{}", std::process::id()));
    let result = std::fs::File::create(&temp)
        .and_then(|mut file| file.write_all(bytes).and_then(|()| file.sync_all()))
        .and_then(|()| std::fs::rename(&temp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result.with_context(|| format!("writing {}", path.display()))
}

/// Writes `pixels` as a PNG at `path` (atomically), creating its folder.
pub fn write_png(pixels: &image::RgbaImage, path: &Path) -> Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    }
    let mut png = Vec::new();
    pixels
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .with_context(|| format!("encoding {}", path.display()))?;
    write_atomically(path, &png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_png_replaces_the_previous_file_and_reads_back_and_no_temporary_stays() {
        let dir = std::env::temp_dir().join(format!("citystream-files-{}", std::process::id()));
        let path = dir.join("frames").join("frame.png");
        let first = image::RgbaImage::from_pixel(3, 2, image::Rgba([1, 2, 3, 255]));
        write_png(&first, &path).expect("first write");
        let second = image::RgbaImage::from_pixel(3, 2, image::Rgba([9, 8, 7, 255]));
        write_png(&second, &path).expect("second write");
        let read = image::open(&path).expect("read back").to_rgba8();
        assert_eq!(read, second);
        let names: Vec<_> = std::fs::read_dir(path.parent().expect("folder"))
            .expect("list")
            .map(|e| e.expect("entry").file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("frame.png")]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_write_into_a_missing_folder_fails_naming_the_file() {
        let path = Path::new("/nonexistent-citystream-folder/summary.json");
        let error = write_atomically(path, b"{}").expect_err("no such folder");
        assert!(format!("{error:#}").contains("summary.json"), "{error:#}");
    }
}
