//! A TCP proxy on loopback that adds latency and faults between a remote-dataset client and
//! an HTTP server: for the remote tests and the remote loader benchmark.
//!
//! Each request the client sends (one read of the client's socket: HTTP requests are small)
//! waits `delay` before it is forwarded, so every request pays one extra round trip however
//! many share a connection. Faults, by request count over the proxy's life: every
//! `drop_every`-th request closes the connection unanswered (a reset); every
//! `truncate_every`-th forwards only the first bytes of its answer, then closes (a short
//! body); with `fail_mips`, every request for a mip range of `textures.pack` (not its
//! header at offset 0) is answered 503 (a server that keeps failing); with `silent_mips`,
//! never answered at all (a server that hangs).
//!
//! Plain threads and blocking sockets: a thread per connection, each direction copied by
//! its own thread. [`FaultProxy`] stops accepting when dropped.

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

/// What the proxy does to requests.
#[derive(Clone, Copy, Debug, Default)]
pub struct FaultOptions {
    /// Added before each request is forwarded.
    pub delay: Duration,
    /// Every N-th request is dropped unanswered (0: none).
    pub drop_every: u64,
    /// Every N-th request's answer is cut short (0: none).
    pub truncate_every: u64,
    /// Requests for mip ranges of `textures.pack` are answered 503.
    pub fail_mips: bool,
    /// Requests for mip ranges of `textures.pack` are never answered (the connection stays
    /// open until the client gives up).
    pub silent_mips: bool,
}

/// A running proxy; dropping it stops accepting connections.
#[derive(Debug)]
pub struct FaultProxy {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    requests: Arc<AtomicU64>,
    faults: Arc<AtomicU64>,
    accept: Option<JoinHandle<()>>,
}

impl FaultProxy {
    /// Listens on a free loopback port and forwards to `upstream`.
    pub fn start(upstream: SocketAddr, options: FaultOptions) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let requests = Arc::new(AtomicU64::new(0));
        let faults = Arc::new(AtomicU64::new(0));
        let (stop_accept, counts) = (Arc::clone(&stop), (Arc::clone(&requests), Arc::clone(&faults)));
        let accept = std::thread::Builder::new().name("fault-proxy".into()).spawn(move || {
            while !stop_accept.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((client, _)) => {
                        let counts = (Arc::clone(&counts.0), Arc::clone(&counts.1));
                        let _ = std::thread::Builder::new()
                            .name("fault-proxy-conn".into())
                            .spawn(move || serve(client, upstream, options, counts));
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(5)),
                }
            }
        })?;
        Ok(Self {
            addr,
            stop,
            requests,
            faults,
            accept: Some(accept),
        })
    }

    /// Where clients connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Requests seen so far.
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Requests dropped, cut short or failed so far.
    pub fn faults(&self) -> u64 {
        self.faults.load(Ordering::Relaxed)
    }
}

impl Drop for FaultProxy {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(accept) = self.accept.take() {
            let _ = accept.join();
        }
    }
}

/// Whether a request asks for a mip range of the pack (a `Range` not starting at 0).
fn is_mip_request(request: &[u8]) -> bool {
    let text = String::from_utf8_lossy(request);
    let mut lines = text.lines();
    let first = lines.next().unwrap_or("");
    if !first.contains("textures.pack") {
        return false;
    }
    lines
        .filter_map(|l| l.split_once(':'))
        .filter(|(name, _)| name.trim().eq_ignore_ascii_case("range"))
        .any(|(_, value)| !value.trim().starts_with("bytes=0-"))
}

fn serve(mut client: TcpStream, upstream: SocketAddr, options: FaultOptions, counts: (Arc<AtomicU64>, Arc<AtomicU64>)) {
    let (requests, faults) = counts;
    let Ok(mut server) = TcpStream::connect(upstream) else {
        return;
    };
    let _ = client.set_nodelay(true);
    let _ = server.set_nodelay(true);
    // The answer direction: copied by its own thread, cut short on request.
    let truncate_next = Arc::new(AtomicBool::new(false));
    let (Ok(mut server_read), Ok(mut client_write)) = (server.try_clone(), client.try_clone()) else {
        return;
    };
    let truncate = Arc::clone(&truncate_next);
    let answers = std::thread::spawn(move || {
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let n = match server_read.read(&mut buf) {
                Ok(0) | Err(_) => break,
                Ok(n) => n,
            };
            if truncate.swap(false, Ordering::Relaxed) {
                let _ = client_write.write_all(&buf[..n.min(64)]);
                break;
            }
            if client_write.write_all(&buf[..n]).is_err() {
                break;
            }
        }
        let _ = client_write.shutdown(Shutdown::Both);
        let _ = server_read.shutdown(Shutdown::Both);
    });
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        let n = match client.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => n,
        };
        let count = requests.fetch_add(1, Ordering::Relaxed) + 1;
        if options.drop_every > 0 && count.is_multiple_of(options.drop_every) {
            faults.fetch_add(1, Ordering::Relaxed);
            break;
        }
        if options.fail_mips && is_mip_request(&buf[..n]) {
            faults.fetch_add(1, Ordering::Relaxed);
            let _ =
                client.write_all(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
            break;
        }
        if options.silent_mips && is_mip_request(&buf[..n]) {
            faults.fetch_add(1, Ordering::Relaxed);
            // Swallow what the client sends until it hangs up.
            while matches!(client.read(&mut buf), Ok(n) if n > 0) {}
            break;
        }
        if options.truncate_every > 0 && count.is_multiple_of(options.truncate_every) {
            faults.fetch_add(1, Ordering::Relaxed);
            truncate_next.store(true, Ordering::Relaxed);
        }
        if !options.delay.is_zero() {
            std::thread::sleep(options.delay);
        }
        if server.write_all(&buf[..n]).is_err() {
            break;
        }
    }
    let _ = client.shutdown(Shutdown::Both);
    let _ = server.shutdown(Shutdown::Both);
    let _ = answers.join();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mip_requests_are_pack_ranges_past_the_header() {
        let mip = b"GET /city/write-01/textures.pack HTTP/1.1\r\nhost: x\r\nrange: bytes=4096-8191\r\n\r\n";
        let header = b"GET /city/write-01/textures.pack HTTP/1.1\r\nRange: bytes=0-63\r\n\r\n";
        let scene = b"GET /city/write-01/scene.bin HTTP/1.1\r\nrange: bytes=10-20\r\n\r\n";
        assert!(is_mip_request(mip));
        assert!(!is_mip_request(header));
        assert!(!is_mip_request(scene));
    }
}
