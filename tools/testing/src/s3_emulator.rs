//! An S3-compatible server on loopback for the remote-dataset tests: moto's server mode
//! (from PyPI, installed by `tools/scripts/setup.sh` into a virtual environment of its own),
//! started on a free port and stopped when dropped. Objects live in its memory; path-style
//! requests, range reads and SigV4-signed requests from any credentials.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context, Result};

use crate::server_process::{wait_until_listening, KilledOnDrop};

/// Credentials the emulator is given (it accepts any; the client signs with them).
pub const ACCESS_KEY_ID: &str = "citystream";
/// See [`ACCESS_KEY_ID`].
pub const SECRET_ACCESS_KEY: &str = "citystream-secret";
/// The region buckets are made in.
pub const REGION: &str = "us-east-1";

/// Uploads a directory tree: `python UPLOAD ENDPOINT BUCKET PREFIX DIR`.
const UPLOAD_SCRIPT: &str = r#"
import os, sys, boto3
endpoint, bucket, prefix, root, key_id, secret, region = sys.argv[1:8]
s3 = boto3.client("s3", endpoint_url=endpoint, aws_access_key_id=key_id,
                  aws_secret_access_key=secret, region_name=region)
if bucket not in [b["Name"] for b in s3.list_buckets().get("Buckets", [])]:
    s3.create_bucket(Bucket=bucket)
count = 0
for folder, _, files in os.walk(root):
    for name in files:
        path = os.path.join(folder, name)
        relative = os.path.relpath(path, root).replace(os.sep, "/")
        s3.upload_file(path, bucket, "/".join(p for p in (prefix.strip("/"), relative) if p))
        count += 1
print(count)
"#;

/// The emulator's installation directory (`CITYSTREAM_S3_EMULATOR_DIR`, else
/// `/opt/citystream/s3-emulator`).
fn install_dir() -> PathBuf {
    std::env::var_os("CITYSTREAM_S3_EMULATOR_DIR")
        .map_or_else(|| PathBuf::from("/opt/citystream/s3-emulator"), PathBuf::from)
}

/// The emulator's server script, if installed.
pub fn binary() -> Option<PathBuf> {
    Some(install_dir().join("bin").join("moto_server")).filter(|p| p.exists())
}

/// A running emulator, stopped on drop.
#[derive(Debug)]
pub struct S3Emulator {
    _child: KilledOnDrop,
    port: u16,
}

impl S3Emulator {
    /// Starts the emulator on a free loopback port; its log goes to `work/s3-emulator.log`.
    pub fn start(work: &Path) -> Result<Self> {
        let binary = binary().context("the S3 emulator is not installed (`make setup` installs it)")?;
        std::fs::create_dir_all(work).with_context(|| format!("creating {}", work.display()))?;
        let log_path = work.join("s3-emulator.log");
        let log = std::fs::File::create(&log_path).with_context(|| format!("creating {}", log_path.display()))?;
        // Port 0: the server binds a free port and prints it; no race with other tests.
        let mut child = Command::new(&binary)
            .args(["-H", "127.0.0.1", "-p", "0"])
            .env("PYTHONUNBUFFERED", "1")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", binary.display()))?;
        let announced = || announced_port(&std::fs::read_to_string(&log_path).unwrap_or_default());
        if let Some(port) = wait_until_listening(&mut child, Duration::from_secs(60), announced)? {
            return Ok(Self {
                _child: KilledOnDrop(child),
                port,
            });
        }
        bail!(
            "the S3 emulator did not start: {}",
            std::fs::read_to_string(&log_path).unwrap_or_default()
        )
    }

    /// The port it listens on (127.0.0.1).
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Its endpoint URL, `http://127.0.0.1:PORT`.
    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// The environment a client needs to reach it: endpoint, credentials, region.
    pub fn client_env(&self) -> Vec<(&'static str, String)> {
        vec![
            ("AWS_ENDPOINT_URL", self.endpoint()),
            ("AWS_ACCESS_KEY_ID", ACCESS_KEY_ID.into()),
            ("AWS_SECRET_ACCESS_KEY", SECRET_ACCESS_KEY.into()),
            ("AWS_REGION", REGION.into()),
        ]
    }

    /// Uploads every file under `dir` to `s3://BUCKET/PREFIX/…` (creating the bucket);
    /// returns the number of files.
    pub fn upload_dir(&self, bucket: &str, prefix: &str, dir: &Path) -> Result<usize> {
        let python = install_dir().join("bin").join("python");
        let out = Command::new(&python)
            .arg("-c")
            .arg(UPLOAD_SCRIPT)
            .arg(self.endpoint())
            .arg(bucket)
            .arg(prefix)
            .arg(dir)
            .args([ACCESS_KEY_ID, SECRET_ACCESS_KEY, REGION])
            .output()
            .with_context(|| format!("running {}", python.display()))?;
        if !out.status.success() {
            bail!(
                "uploading {} to s3://{bucket}/{prefix}: {}",
                dir.display(),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        String::from_utf8_lossy(&out.stdout)
            .trim()
            .parse()
            .context("the upload script's file count")
    }
}

/// The port in the server's "Running on http://127.0.0.1:PORT" line.
fn announced_port(log: &str) -> Option<u16> {
    let at = log.find("Running on http://127.0.0.1:")? + "Running on http://127.0.0.1:".len();
    let digits: String = log[at..].chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok().filter(|&p| p != 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_announced_port_is_read_through_colour_codes() {
        let log = "\u{1b}[31mWARNING: development server\u{1b}[0m\n * Running on http://127.0.0.1:32909\n";
        assert_eq!(announced_port(log), Some(32909));
        assert_eq!(announced_port(" * Running on http://127.0.0.1:"), None);
        assert_eq!(announced_port("nothing yet"), None);
    }
}
