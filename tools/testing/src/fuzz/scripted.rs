//! The remote harness: a scripted loopback HTTP server whose every answer is the input,
//! and the answers it starts from.

use anyhow::Result;

use super::input::{Outcome, Seed};

/// A loopback HTTP server that answers every request with the current input and closes the
/// connection, and a remote store reading from it.
#[derive(Debug)]
pub(crate) struct ScriptedServer {
    answer: std::sync::Arc<std::sync::Mutex<Vec<u8>>>,
    url: String,
    /// Replaced after an input that waited out the timeout: a store that saw its server go
    /// silent fails later reads at once, which would hide every later input's answer.
    store: std::sync::Mutex<citystream_dataset::remote::RemoteStore>,
}

/// The scripted server's store: no retries (every answer is the same input), a short timeout
/// for answers that promise more than they send (the server closes at once anyway).
fn scripted_store(url: &str) -> Result<citystream_dataset::remote::RemoteStore> {
    let options = citystream_dataset::remote::RemoteOptions {
        retries: 0,
        timeout: SCRIPTED_TIMEOUT,
        connect_timeout: SCRIPTED_TIMEOUT,
        ..Default::default()
    };
    Ok(citystream_dataset::remote::RemoteStore::new(url, &options)?)
}

const SCRIPTED_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(2);

impl ScriptedServer {
    pub(crate) fn start() -> Result<Self> {
        use std::io::{Read, Write};
        let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
        let url = format!("http://{}/city/", listener.local_addr()?);
        let answer = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let served = std::sync::Arc::clone(&answer);
        std::thread::Builder::new().name("fuzz-http".into()).spawn(move || {
            for mut stream in listener.incoming().flatten() {
                // The request (small) in one read; its content does not matter.
                let mut request = [0u8; 4096];
                let _ = stream.read(&mut request);
                let bytes = served.lock().map(|a| a.clone()).unwrap_or_default();
                let _ = stream.write_all(&bytes);
                let _ = stream.shutdown(std::net::Shutdown::Both);
            }
        })?;
        let store = std::sync::Mutex::new(scripted_store(&url)?);
        Ok(Self { answer, url, store })
    }

    pub(crate) fn run(&self, bytes: &[u8]) -> Outcome {
        use citystream_dataset::DatasetStore;
        if let Ok(mut answer) = self.answer.lock() {
            *answer = bytes.to_vec();
        }
        let Ok(mut store) = self.store.lock() else {
            return Outcome::Rejected;
        };
        let started = std::time::Instant::now();
        let path = store.root().join("file.bin");
        let _ = store.len(&path);
        let mut buf = [0u8; 32];
        let outcome = match store.read_at(&path, 0, &mut buf) {
            Ok(()) => Outcome::Accepted,
            Err(_) => Outcome::Rejected,
        };
        if started.elapsed() >= SCRIPTED_TIMEOUT {
            if let Ok(fresh) = scripted_store(&self.url) {
                *store = fresh;
            }
        }
        outcome
    }
}

/// Answers a server may give to a length (HEAD) and a 32-byte range request: partial content
/// with its range, and ones the client refuses (`refused-…`): the whole file for a range, a
/// redirect to another origin, errors, a body without a length.
pub(crate) fn remote_seeds() -> Vec<Seed> {
    let body: Vec<u8> = (0..32u8).collect();
    let answer = |head: &str, body: &[u8]| {
        let mut bytes = head.replace('\n', "\r\n").into_bytes();
        bytes.extend_from_slice(body);
        bytes
    };
    let seeds = [
        (
            "partial.http",
            answer(
                "HTTP/1.1 206 Partial Content\nContent-Range: bytes 0-31/4096\nContent-Length: 32\nAccept-Ranges: bytes\n\n",
                &body,
            ),
        ),
        ("refused-whole-file-for-a-range.http", answer("HTTP/1.1 200 OK\nContent-Length: 32\n\n", &body)),
        (
            "refused-redirect-elsewhere.http",
            answer("HTTP/1.1 302 Found\nLocation: http://127.0.0.1:9/city/file.bin\nContent-Length: 0\n\n", &[]),
        ),
        ("refused-unavailable.http", answer("HTTP/1.1 503 Service Unavailable\nContent-Length: 0\n\n", &[])),
        ("refused-missing.http", answer("HTTP/1.1 404 Not Found\nContent-Length: 9\n\n", b"not found")),
        (
            "refused-chunked-without-length.http",
            answer(
                "HTTP/1.1 206 Partial Content\nContent-Range: bytes 0-31/32\nTransfer-Encoding: chunked\n\n",
                b"20\r\n\x00\x01\x02\x03\x04\x05\x06\x07\x08\x09\x0a\x0b\x0c\x0d\x0e\x0f\x10\x11\x12\x13\x14\x15\x16\x17\x18\x19\x1a\x1b\x1c\x1d\x1e\x1f\r\n0\r\n\r\n",
            ),
        ),
    ];
    seeds
        .into_iter()
        .map(|(name, bytes)| Seed {
            name: name.to_owned(),
            bytes,
        })
        .collect()
}
