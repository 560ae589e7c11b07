//! Waiting for a server process the benchmarks and tests start (nginx, the S3 emulator) to
//! listen on loopback.

use std::process::Child;
use std::time::{Duration, Instant};

/// A child process (a server a test or benchmark started) killed and reaped when dropped.
#[derive(Debug)]
pub struct KilledOnDrop(pub Child);

impl Drop for KilledOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Polls until `child` accepts connections on the port `port` names (a fixed one, or one
/// read from its log once it says), within `limit`. `None` when it exits first or the time
/// runs out; it is then killed and reaped, and the caller reports its log.
pub fn wait_until_listening(
    child: &mut Child,
    limit: Duration,
    mut port: impl FnMut() -> Option<u16>,
) -> std::io::Result<Option<u16>> {
    let started = Instant::now();
    while started.elapsed() < limit {
        if let Some(port) = port() {
            if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
                return Ok(Some(port));
            }
        }
        if child.try_wait()?.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let _ = child.kill();
    let _ = child.wait();
    Ok(None)
}
