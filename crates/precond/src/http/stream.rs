//! Large answers written as they are read: a producer on a blocking thread writes into a
//! [`std::io::Write`] whose bytes go to the client in chunks of [`CHUNK_BYTES`], at most
//! [`CHUNKS_IN_FLIGHT`] ahead of what the client has read.
//!
//! What one such answer holds is therefore bounded by the chunks in flight and the producer's
//! own working set, never by the answer's size; the producer runs off the async workers; a
//! client that leaves ends the producer at its next write, and one that stops reading for
//! [`STALL`] ends it too (the connection is then closed mid-body, which the client sees as a
//! truncated answer). How many run at once is the service's export gate.

use axum::body::{Body, Bytes};
use std::io::Write;
use std::time::Duration;
use tokio::sync::mpsc;

/// Bytes sent to the client at a time.
pub const CHUNK_BYTES: usize = 64 * 1024;

/// Chunks the producer may be ahead of the client.
pub const CHUNKS_IN_FLIGHT: usize = 4;

/// How long a producer waits for a client that does not read before it gives up.
pub const STALL: Duration = Duration::from_secs(30);

/// A body written by `produce` from `source` on a blocking thread; `source` (which holds an
/// export slot) is dropped when the producer ends. An error of the producer (or a client that
/// left or stalled) ends the body early; the error is logged.
pub fn produced_body<S: Send + 'static>(
    mut source: S,
    what: &'static str,
    produce: impl FnOnce(&mut S, &mut ChunkWriter) -> std::io::Result<()> + Send + 'static,
) -> Body {
    let (tx, rx) = mpsc::channel::<Result<Bytes, std::io::Error>>(CHUNKS_IN_FLIGHT);
    let handle = tokio::runtime::Handle::current();
    tokio::task::spawn_blocking(move || {
        let mut writer = ChunkWriter {
            tx,
            handle,
            buffer: Vec::with_capacity(CHUNK_BYTES),
        };
        let outcome = produce(&mut source, &mut writer).and_then(|()| writer.flush());
        drop(source);
        if let Err(e) = outcome {
            tracing::warn!(error = %e, answer = what, "a streamed answer ended early");
            // Best effort: tell the body it is incomplete (the client may be gone).
            let _ = writer.tx.try_send(Err(e));
        }
    });
    Body::from_stream(tokio_stream_from(rx))
}

/// The receiving end as a stream of chunks.
fn tokio_stream_from(
    mut rx: mpsc::Receiver<Result<Bytes, std::io::Error>>,
) -> impl futures_util::Stream<Item = Result<Bytes, std::io::Error>> + Send + 'static {
    futures_util::stream::poll_fn(move |cx| rx.poll_recv(cx))
}

/// Writes into the body, a chunk at a time; see the module documentation.
pub struct ChunkWriter {
    tx: mpsc::Sender<Result<Bytes, std::io::Error>>,
    handle: tokio::runtime::Handle,
    buffer: Vec<u8>,
}

impl ChunkWriter {
    /// Runs `future` to completion on the server's runtime from the producer's thread (a
    /// database read between chunks).
    pub fn block_on<F: std::future::Future>(&self, future: F) -> F::Output {
        self.handle.block_on(future)
    }

    fn send(&mut self) -> std::io::Result<()> {
        if self.buffer.is_empty() {
            return Ok(());
        }
        let chunk = Bytes::from(std::mem::replace(
            &mut self.buffer,
            Vec::with_capacity(CHUNK_BYTES),
        ));
        match self.handle.block_on(self.tx.send_timeout(Ok(chunk), STALL)) {
            Ok(()) => Ok(()),
            Err(mpsc::error::SendTimeoutError::Closed(_)) => Err(std::io::Error::new(
                std::io::ErrorKind::BrokenPipe,
                "the client left",
            )),
            Err(mpsc::error::SendTimeoutError::Timeout(_)) => Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!("the client read nothing for {} s", STALL.as_secs()),
            )),
        }
    }
}

impl Write for ChunkWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let room = CHUNK_BYTES - self.buffer.len();
        let n = data.len().min(room);
        self.buffer.extend_from_slice(&data[..n]);
        if self.buffer.len() >= CHUNK_BYTES {
            self.send()?;
        }
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.send()
    }
}
