//! Live experiments: the in-memory side of stored experiments — the built domain (and, once
//! fitted, the current model) — loaded from the store on first use and kept for the process's
//! life.

use crate::domain::Domain;
use crate::error::Error;
use crate::settings::ExperimentSettings;
use crate::store::Store;
use std::collections::HashMap;
use std::sync::{Arc, RwLock};

/// One experiment's settings and the domain built from them.
#[derive(Debug)]
pub struct LiveExperiment {
    /// Identifier.
    pub id: i64,
    /// Resolved settings.
    pub settings: ExperimentSettings,
    /// The domain built from `settings.domain`.
    pub domain: Arc<dyn Domain>,
}

/// Every experiment this process has touched.
#[derive(Debug, Default)]
pub struct Registry {
    experiments: RwLock<HashMap<i64, Arc<LiveExperiment>>>,
}

impl Registry {
    /// Adds a just-created experiment.
    pub fn insert(&self, live: LiveExperiment) -> Arc<LiveExperiment> {
        let live = Arc::new(live);
        self.experiments
            .write()
            .unwrap_or_else(|p| p.into_inner())
            .insert(live.id, live.clone());
        live
    }

    /// The live experiment `id`, loading it from the store if needed; 404 if it does not exist.
    pub async fn get(&self, store: &Store, id: i64) -> Result<Arc<LiveExperiment>, Error> {
        if let Some(live) = self
            .experiments
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .get(&id)
        {
            return Ok(live.clone());
        }
        let stored = store
            .experiment(id)
            .await?
            .ok_or_else(|| Error::NotFound(format!("no experiment {id}")))?;
        let domain = stored.settings.domain.build().map_err(|e| {
            Error::Internal(anyhow::anyhow!(
                "stored experiment {id} no longer builds: {e}"
            ))
        })?;
        let live = LiveExperiment {
            id,
            settings: stored.settings,
            domain,
        };
        Ok(self.insert(live))
    }
}
