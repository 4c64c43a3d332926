//! Retries of store reads that failed for a reason that may pass (a dropped connection,
//! a 5xx answer after the client's own retries): with backoff, within a budget, logged.
//! A permanent error (a missing file, a bad schema, a refused permission) fails at once.

use crate::error::{Result, TrainError};
use osrt_retry::RetryPolicy;
use std::future::Future;
use std::time::Duration;

/// How long a read may keep failing transiently before the error stands.
pub const READ_RETRY_BUDGET: Duration = Duration::from_secs(60);

impl TrainError {
    /// Whether the error may pass if the same call is made again.
    pub fn is_transient(&self) -> bool {
        matches!(self, TrainError::Dataset(d) if d.is_transient())
    }
}

/// Runs `call` until it succeeds, fails permanently, or `budget` is spent, under
/// [`RetryPolicy::backoff`] (0.2 s after the first failure, doubling up to 5 s).
pub async fn retry_transient<T, F, Fut>(what: &str, budget: Duration, call: F) -> Result<T>
where
    F: FnMut() -> Fut,
    Fut: Future<Output = Result<T>>,
{
    RetryPolicy::backoff(budget)
        .run(what, TrainError::is_transient, call)
        .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use osrt_dataset::DatasetError;
    use std::cell::Cell;

    fn store_error(source: object_store::Error) -> TrainError {
        TrainError::Dataset(DatasetError::Store {
            path: "s3://bucket/data/train/part-00000.parquet".into(),
            source,
        })
    }

    fn reset() -> object_store::Error {
        object_store::Error::Generic {
            store: "S3",
            source: "connection reset by peer".into(),
        }
    }

    #[tokio::test]
    async fn transient_errors_are_retried_and_permanent_ones_are_not() {
        let calls = Cell::new(0);
        let v = retry_transient("listing", Duration::from_secs(10), || {
            calls.set(calls.get() + 1);
            let n = calls.get();
            async move {
                if n < 3 {
                    Err(store_error(reset()))
                } else {
                    Ok(n)
                }
            }
        })
        .await
        .unwrap();
        assert_eq!(v, 3);
        calls.set(0);
        let e = retry_transient("listing", Duration::from_secs(10), || {
            calls.set(calls.get() + 1);
            async {
                Err::<(), _>(store_error(object_store::Error::NotFound {
                    path: "x".into(),
                    source: "no such key".into(),
                }))
            }
        })
        .await
        .unwrap_err();
        assert_eq!(calls.get(), 1, "a missing file fails at once: {e}");
        // A budget spent: the last transient error stands.
        calls.set(0);
        let e = retry_transient("listing", Duration::from_millis(500), || {
            calls.set(calls.get() + 1);
            async { Err::<(), _>(store_error(reset())) }
        })
        .await
        .unwrap_err();
        assert!(e.is_transient() && calls.get() >= 2, "{e}");
    }

    #[test]
    fn a_store_error_inside_a_parquet_read_is_transient_a_bad_file_is_not() {
        let inside = DatasetError::Parquet {
            path: "p".into(),
            source: parquet::errors::ParquetError::External(Box::new(reset())),
        };
        assert!(inside.is_transient());
        let corrupt = DatasetError::Parquet {
            path: "p".into(),
            source: parquet::errors::ParquetError::General("bad footer".into()),
        };
        assert!(!corrupt.is_transient());
    }
}
