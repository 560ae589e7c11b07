//! The Vulkan instance: loader, validation layer and debug messenger.

use std::ffi::{c_void, CStr, CString};
use std::sync::{Arc, Mutex};

use ash::vk;

use crate::error::{EngineError, Result, VkResultExt};

/// The Khronos validation layer's name.
pub const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

/// One message from the debug messenger.
#[derive(Clone, Debug)]
pub struct ValidationMessage {
    /// Severity as Vulkan reported it.
    pub severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    /// The message id name (e.g. `VUID-...`), empty when absent.
    pub id: String,
    /// The message text.
    pub text: String,
}

impl ValidationMessage {
    /// Whether this message is a validation error.
    pub fn is_error(&self) -> bool {
        self.severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR)
    }
}

/// Collects the messages the debug messenger receives.
///
/// Threading: the messenger may call in from any thread that makes Vulkan
/// calls; the log is internally locked.
#[derive(Debug, Default)]
pub struct ValidationLog {
    messages: Mutex<Vec<ValidationMessage>>,
}

impl ValidationLog {
    fn push(&self, message: ValidationMessage) {
        // A poisoned lock only means another thread panicked while pushing;
        // the vector itself is still valid.
        let mut messages = self.messages.lock().unwrap_or_else(|e| e.into_inner());
        messages.push(message);
    }

    /// All messages so far.
    pub fn messages(&self) -> Vec<ValidationMessage> {
        self.messages.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// The validation errors so far.
    pub fn errors(&self) -> Vec<ValidationMessage> {
        self.messages()
            .into_iter()
            .filter(ValidationMessage::is_error)
            .collect()
    }

    /// Number of validation errors so far.
    pub fn error_count(&self) -> usize {
        self.errors().len()
    }
}

/// Options for creating the instance.
#[derive(Clone, Debug)]
pub struct InstanceOptions {
    /// Enable `VK_LAYER_KHRONOS_validation` and fail if it is missing.
    pub validation: bool,
    /// Also enable the layer's synchronization validation (hazards between
    /// commands, submissions and frames in flight). Implies `validation`.
    pub synchronization: bool,
    /// Application name reported to the driver.
    pub app_name: String,
    /// Further instance extensions to enable, e.g. the surface extensions a
    /// window needs (`present::instance_extensions`). Each must be available.
    pub extensions: Vec<CString>,
}

impl Default for InstanceOptions {
    fn default() -> Self {
        Self {
            validation: default_validation(),
            synchronization: default_synchronization_validation(),
            app_name: "citystream".to_owned(),
            extensions: Vec::new(),
        }
    }
}

/// The environment variable that turns validation on (`1`), on with
/// synchronization validation (`sync`) or off (`0`).
pub const VALIDATION_ENV: &str = "CITYSTREAM_VALIDATION";

/// Validation is on in debug builds and whenever `CITYSTREAM_VALIDATION` is
/// `1` or `sync`; `CITYSTREAM_VALIDATION=0` turns it off.
pub fn default_validation() -> bool {
    match std::env::var(VALIDATION_ENV).as_deref() {
        Ok("1") | Ok("sync") => true,
        Ok("0") => false,
        _ => cfg!(debug_assertions),
    }
}

/// Synchronization validation is on when `CITYSTREAM_VALIDATION=sync`.
pub fn default_synchronization_validation() -> bool {
    std::env::var(VALIDATION_ENV).as_deref() == Ok("sync")
}

/// Owns the `VkInstance` and its debug messenger.
pub struct Instance {
    pub(crate) entry: ash::Entry,
    pub(crate) raw: ash::Instance,
    debug: Option<(ash::ext::debug_utils::Instance, vk::DebugUtilsMessengerEXT)>,
    log: Arc<ValidationLog>,
    /// Keeps the log alive for as long as the messenger may call back into it.
    log_for_callback: *const ValidationLog,
    validation: bool,
}

// SAFETY: `log_for_callback` is an `Arc` raw pointer only dereferenced by the
// messenger callback and released in `Drop`; every other field is Send + Sync.
unsafe impl Send for Instance {}
// SAFETY: as above; `ValidationLog` is internally locked.
unsafe impl Sync for Instance {}

debug_fields!(Instance { raw = |s| s.raw.handle(), validation });

impl Instance {
    /// Loads Vulkan and creates an instance (API 1.3).
    pub fn new(options: &InstanceOptions) -> Result<Self> {
        // SAFETY: loading the system Vulkan loader runs its initialisers; we
        // trust the installed libvulkan.
        let entry = unsafe { ash::Entry::load() }.map_err(|e| EngineError::Loader(e.to_string()))?;

        let mut layers: Vec<*const std::ffi::c_char> = Vec::new();
        let mut extensions: Vec<*const std::ffi::c_char> = Vec::new();
        // SAFETY: plain enumeration call on a loaded entry.
        let available_extensions = unsafe { entry.enumerate_instance_extension_properties(None) }
            .vk("vkEnumerateInstanceExtensionProperties")?;
        let has_debug_utils = available_extensions.iter().any(|e| {
            e.extension_name_as_c_str()
                .is_ok_and(|n| n == ash::ext::debug_utils::NAME)
        });
        let validation = options.validation || options.synchronization;
        let mut validation_features = false;
        if validation {
            // SAFETY: plain enumeration call on a loaded entry.
            let available_layers =
                unsafe { entry.enumerate_instance_layer_properties() }.vk("vkEnumerateInstanceLayerProperties")?;
            let present = available_layers
                .iter()
                .any(|l| l.layer_name_as_c_str().is_ok_and(|n| n == VALIDATION_LAYER));
            if !present {
                return Err(EngineError::LayerMissing(
                    VALIDATION_LAYER.to_string_lossy().into_owned(),
                ));
            }
            layers.push(VALIDATION_LAYER.as_ptr());
            if options.synchronization {
                // SAFETY: plain enumeration call on a loaded entry for an installed layer.
                let layer_extensions = unsafe { entry.enumerate_instance_extension_properties(Some(VALIDATION_LAYER)) }
                    .vk("vkEnumerateInstanceExtensionProperties (validation layer)")?;
                validation_features = layer_extensions.iter().any(|e| {
                    e.extension_name_as_c_str()
                        .is_ok_and(|n| n == ash::ext::validation_features::NAME)
                });
                if !validation_features {
                    return Err(EngineError::LayerMissing(format!(
                        "{} with {} (needed for synchronization validation)",
                        VALIDATION_LAYER.to_string_lossy(),
                        ash::ext::validation_features::NAME.to_string_lossy()
                    )));
                }
                extensions.push(ash::ext::validation_features::NAME.as_ptr());
            }
        }
        if has_debug_utils {
            extensions.push(ash::ext::debug_utils::NAME.as_ptr());
        }
        for wanted in &options.extensions {
            let available = available_extensions
                .iter()
                .any(|e| e.extension_name_as_c_str().is_ok_and(|n| n == wanted.as_c_str()));
            if !available {
                return Err(EngineError::ExtensionMissing(wanted.to_string_lossy().into_owned()));
            }
            extensions.push(wanted.as_ptr());
        }

        let app_name = CString::new(options.app_name.replace('\0', " ")).unwrap_or_default();
        let app_info = vk::ApplicationInfo::default()
            .application_name(&app_name)
            .engine_name(c"citystream")
            .api_version(vk::API_VERSION_1_3);
        let enabled_features = [vk::ValidationFeatureEnableEXT::SYNCHRONIZATION_VALIDATION];
        let mut features = vk::ValidationFeaturesEXT::default().enabled_validation_features(&enabled_features);
        let mut create_info = vk::InstanceCreateInfo::default()
            .application_info(&app_info)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&extensions);
        if validation_features {
            create_info = create_info.push_next(&mut features);
        }
        // SAFETY: every pointer in create_info refers to data alive for this call.
        let raw = unsafe { entry.create_instance(&create_info, None) }.vk("vkCreateInstance")?;

        let log = Arc::new(ValidationLog::default());
        let log_for_callback = Arc::into_raw(Arc::clone(&log));
        let mut instance = Self {
            entry,
            raw,
            debug: None,
            log,
            log_for_callback,
            validation,
        };
        if has_debug_utils {
            let loader = ash::ext::debug_utils::Instance::new(&instance.entry, &instance.raw);
            let info = vk::DebugUtilsMessengerCreateInfoEXT::default()
                .message_severity(
                    vk::DebugUtilsMessageSeverityFlagsEXT::ERROR | vk::DebugUtilsMessageSeverityFlagsEXT::WARNING,
                )
                .message_type(
                    vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                        | vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                        | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
                )
                .pfn_user_callback(Some(debug_callback))
                .user_data(instance.log_for_callback as *mut c_void);
            // SAFETY: the callback's user data outlives the messenger (released in Drop after it).
            let messenger =
                unsafe { loader.create_debug_utils_messenger(&info, None) }.vk("vkCreateDebugUtilsMessengerEXT")?;
            instance.debug = Some((loader, messenger));
        }
        Ok(instance)
    }

    /// The messages the debug messenger collected.
    pub fn validation_log(&self) -> &Arc<ValidationLog> {
        &self.log
    }

    /// Whether the validation layer is enabled.
    pub fn validation_enabled(&self) -> bool {
        self.validation
    }

    /// The raw `ash` instance.
    pub fn raw(&self) -> &ash::Instance {
        &self.raw
    }

    /// Debug-utils instance functions, when the extension is present.
    pub(crate) fn has_debug_utils(&self) -> bool {
        self.debug.is_some()
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        if let Some((loader, messenger)) = self.debug.take() {
            // SAFETY: the messenger was created from this instance and is destroyed once.
            unsafe { loader.destroy_debug_utils_messenger(messenger, None) };
        }
        // SAFETY: the owning Device destroyed the logical device before this
        // drop runs (field order), so no child object remains.
        unsafe { self.raw.destroy_instance(None) };
        // SAFETY: balances the Arc::into_raw in `new`; the messenger is gone.
        drop(unsafe { Arc::from_raw(self.log_for_callback) });
    }
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user_data: *mut c_void,
) -> vk::Bool32 {
    if data.is_null() || user_data.is_null() {
        return vk::FALSE;
    }
    // SAFETY: the driver passes valid callback data for the duration of the call.
    let data = unsafe { &*data };
    let text = if data.p_message.is_null() {
        String::new()
    } else {
        // SAFETY: p_message is a NUL-terminated string owned by the driver for this call.
        unsafe { CStr::from_ptr(data.p_message) }.to_string_lossy().into_owned()
    };
    let id = if data.p_message_id_name.is_null() {
        String::new()
    } else {
        // SAFETY: as above.
        unsafe { CStr::from_ptr(data.p_message_id_name) }
            .to_string_lossy()
            .into_owned()
    };
    let message = ValidationMessage { severity, id, text };
    if message.is_error() {
        eprintln!("[vulkan validation error] {}: {}", message.id, message.text);
    } else if std::env::var_os("CITYSTREAM_VULKAN_WARNINGS").is_some() {
        eprintln!("[vulkan warning] {}: {}", message.id, message.text);
    }
    // SAFETY: user_data is the ValidationLog pointer kept alive by Instance.
    let log = unsafe { &*(user_data as *const ValidationLog) };
    log.push(message);
    vk::FALSE
}
