//! nginx (Debian's `nginx-light`) serving a directory on a loopback port, for the remote
//! benchmark and tests: started with a configuration written into a work directory (no
//! system files touched), in the foreground, and stopped when dropped. Static files get
//! range requests, which is all a remote dataset needs.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context, Result};

use crate::server_process::{wait_until_listening, KilledOnDrop};

/// A running nginx, stopped on drop.
#[derive(Debug)]
pub struct Nginx {
    _child: KilledOnDrop,
    port: u16,
    /// Where it logs each request (the requests a test made, with their query strings).
    access_log: PathBuf,
}

/// The nginx binary, if installed.
pub fn binary() -> Option<PathBuf> {
    ["/usr/sbin/nginx", "/usr/bin/nginx"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
}

impl Nginx {
    /// Serves `root` on a free loopback port; its configuration, logs and temporary files
    /// go to `work`.
    pub fn start(work: &Path, root: &Path) -> Result<Self> {
        let binary = binary().context("nginx is not installed (`make setup` installs nginx-light)")?;
        let root = std::path::absolute(root).with_context(|| format!("resolving {}", root.display()))?;
        let work = std::path::absolute(work).with_context(|| format!("resolving {}", work.display()))?;
        let temp = work.join("nginx-temp");
        std::fs::create_dir_all(&temp).with_context(|| format!("creating {}", temp.display()))?;
        // Errors before the configuration's error_log applies go to standard error.
        let stderr_path = work.join("nginx-stderr.log");
        for _ in 0..5 {
            // A port the system just handed out is free unless taken meanwhile; then nginx
            // fails to bind and another is tried.
            let port = TcpListener::bind("127.0.0.1:0")
                .and_then(|l| l.local_addr())
                .context("finding a free port")?
                .port();
            let conf = work.join("nginx.conf");
            std::fs::write(
                &conf,
                format!(
                    "daemon off;\nmaster_process off;\nworker_processes 1;\npid {work}/nginx.pid;\n\
                     error_log {work}/nginx-error.log;\nevents {{ worker_connections 1024; }}\n\
                     http {{\n  access_log {work}/nginx-access.log;\n  client_body_temp_path {temp};\n  proxy_temp_path {temp};\n  \
                     fastcgi_temp_path {temp};\n  uwsgi_temp_path {temp};\n  scgi_temp_path {temp};\n  \
                     keepalive_requests 100000;\n  server {{ listen 127.0.0.1:{port}; root {root}; }}\n}}\n",
                    work = work.display(),
                    temp = temp.display(),
                    root = root.display(),
                ),
            )
            .with_context(|| format!("writing {}", conf.display()))?;
            let mut child = Command::new(&binary)
                .arg("-c")
                .arg(&conf)
                .arg("-p")
                .arg(&work)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(
                    std::fs::File::create(&stderr_path)
                        .with_context(|| format!("creating {}", stderr_path.display()))?,
                )
                .spawn()
                .with_context(|| format!("starting {}", binary.display()))?;
            if wait_until_listening(&mut child, Duration::from_secs(10), || Some(port))?.is_some() {
                return Ok(Self {
                    _child: KilledOnDrop(child),
                    port,
                    access_log: work.join("nginx-access.log"),
                });
            }
        }
        bail!(
            "nginx did not start: {}{}",
            std::fs::read_to_string(&stderr_path).unwrap_or_default(),
            std::fs::read_to_string(work.join("nginx-error.log")).unwrap_or_default()
        )
    }

    /// The port it listens on (127.0.0.1).
    pub fn port(&self) -> u16 {
        self.port
    }

    /// `http://127.0.0.1:PORT/path`.
    pub fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}/{path}", self.port)
    }

    /// The request lines served so far (method, path with its query, protocol), oldest first.
    pub fn requests(&self) -> Vec<String> {
        std::fs::read_to_string(&self.access_log)
            .unwrap_or_default()
            .lines()
            .filter_map(|line| line.split('"').nth(1).map(str::to_owned))
            .collect()
    }
}
