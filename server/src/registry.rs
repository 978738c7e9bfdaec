//! Objects of one kind (a tenant's accels, its buffers) under a server-given id and an optional name that is unique
//! among them.

use dashmap::DashMap;
use dashmap::mapref::entry::Entry;

use crate::error::{ServiceError, ServiceResult};

/// A concurrent map from ids to objects, with an index from names to ids.
#[derive(Debug)]
pub struct Registry<T> {
    /// What the objects are, for errors: `accel`, `buffer`.
    what: &'static str,
    /// Objects by id.
    by_id: DashMap<String, T>,
    /// Ids by name, for named objects.
    ids_by_name: DashMap<String, String>,
}

impl<T: Clone> Registry<T> {
    /// An empty registry of `what`s.
    pub fn new(what: &'static str) -> Self {
        Registry { what, by_id: DashMap::new(), ids_by_name: DashMap::new() }
    }

    /// Objects held.
    pub fn len(&self) -> usize {
        self.by_id.len()
    }

    /// Fails with ALREADY_EXISTS if `name` is taken.
    pub fn check_free(&self, name: &str) -> ServiceResult<()> {
        if self.ids_by_name.contains_key(name) {
            return Err(ServiceError::AlreadyExists { what: self.what, name: name.into() });
        }
        Ok(())
    }

    /// Adds `value` under `id` and `name` (empty: no name); fails with ALREADY_EXISTS if the name was taken
    /// meanwhile.
    pub fn insert(&self, id: String, name: &str, value: T) -> ServiceResult<()> {
        if !name.is_empty() {
            match self.ids_by_name.entry(name.into()) {
                Entry::Occupied(_) => return Err(ServiceError::AlreadyExists { what: self.what, name: name.into() }),
                Entry::Vacant(slot) => {
                    slot.insert(id.clone());
                }
            }
        }
        self.by_id.insert(id, value);
        Ok(())
    }

    /// The object with this id, or else with this name.
    pub fn get(&self, id: Option<&str>, name: Option<&str>) -> ServiceResult<T> {
        let id = match (id, name) {
            (Some(id), _) => id.to_string(),
            (None, Some(name)) => {
                self.ids_by_name.get(name).map(|id| id.clone()).ok_or_else(|| self.not_found(name))?
            }
            (None, None) => return Err(ServiceError::invalid(self.what, "an id or a name is required")),
        };
        self.by_id.get(&id).map(|value| value.clone()).ok_or_else(|| self.not_found(&id))
    }

    /// Puts `value` in the place of the object `id`; NOT_FOUND if there is none.
    pub fn replace(&self, id: &str, value: T) -> ServiceResult<()> {
        let mut slot = self.by_id.get_mut(id).ok_or_else(|| self.not_found(id))?;
        *slot = value;
        Ok(())
    }

    /// Every object, in no particular order.
    pub fn values(&self) -> Vec<T> {
        self.by_id.iter().map(|entry| entry.clone()).collect()
    }

    /// Removes the object `id` (named `name`, or unnamed when empty).
    pub fn remove(&self, id: &str, name: &str) -> ServiceResult<T> {
        let (_, value) = self.by_id.remove(id).ok_or_else(|| self.not_found(id))?;
        if !name.is_empty() {
            self.ids_by_name.remove_if(name, |_, named| named == id);
        }
        Ok(value)
    }

    /// The NOT_FOUND error for `key`.
    fn not_found(&self, key: &str) -> ServiceError {
        ServiceError::NotFound { what: self.what, name: key.into(), field: String::new() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_unique_ids_and_names_both_find_and_removal_frees_the_name() {
        let registry = Registry::new("thing");
        registry.insert("t-1".into(), "a", 1).unwrap();
        registry.insert("t-2".into(), "", 2).unwrap();
        assert!(matches!(registry.insert("t-3".into(), "a", 3), Err(ServiceError::AlreadyExists { .. })));
        assert!(registry.check_free("a").is_err());
        assert_eq!((registry.get(None, Some("a")).unwrap(), registry.get(Some("t-2"), None).unwrap()), (1, 2));
        assert!(matches!(registry.get(Some("t-3"), None), Err(ServiceError::NotFound { .. })));
        assert_eq!(registry.len(), 2);
        assert_eq!(registry.remove("t-1", "a").unwrap(), 1);
        assert!(registry.get(None, Some("a")).is_err());
        registry.check_free("a").unwrap();
        assert!(registry.remove("t-1", "a").is_err());
        assert!(matches!(registry.get(None, None), Err(ServiceError::Invalid { .. })));
        registry.replace("t-2", 20).unwrap();
        assert_eq!(registry.get(Some("t-2"), None).unwrap(), 20);
        assert!(registry.replace("t-1", 10).is_err(), "removed objects cannot be replaced");
    }
}
