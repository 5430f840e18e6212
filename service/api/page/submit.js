// The new-job form: a built-in scene (GET /scenes) or a dropped zip of a scene folder, and the
// job options. Bounds, defaults and choices come from the server's own schema (JobCreate in
// /openapi.json, derived from service/loop/spec.py), so the page states no limit of its own;
// the form does not validate either: the server's 422 message says what is wrong.

import { api } from "./api.js";
import { ParamFields, zipDefaults } from "./params.js";

const NUMBER_FIELDS = ["width", "height", "frames", "spp_first", "max_iterations", "spp_budget", "time_limit",
                       "target_error", "lambda", "seed"];
// Blank means "not this rule": the server stops by the rules given, and by its default iteration
// count only when none is (service/loop/spec.py rules_as_given), so blank is not sent at all.
const RULE_DEFAULTS_AS_PLACEHOLDER = ["max_iterations"];
const DEFAULT_SIZE = 256;  // a first look renders quickly; blank the fields for the scene's own size

function numberSchema(property) {
  return (property.anyOf || [property]).find((s) => s.type === "integer" || s.type === "number") || {};
}

export class SubmitForm {
  constructor(form, {onSubmitted, onError}) {
    this.form = form;
    this.onSubmitted = onSubmitted;
    this.onError = onError;
    this.scenes = [];
    this.bundle = null;
    this.scene = form.querySelector("#scene-select");
    this.description = form.querySelector("#scene-description");
    this.dropZone = form.querySelector("#drop-zone");
    this.fileInput = form.querySelector("#bundle-input");
    this.params = new ParamFields(form.querySelector("#params-list"), form.querySelector("#params-note"));
    form.querySelector("#bundle-xml").addEventListener("change", () => this.readBundleParams());
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      this.submit();
    });
    this.scene.addEventListener("change", () => this.describeScene());
    this.fileInput.addEventListener("change", () => this.useBundle(this.fileInput.files[0] || null));
    form.querySelector("#bundle-clear").addEventListener("click", () => this.useBundle(null));
    this.dropZone.addEventListener("dragover", (event) => {
      event.preventDefault();
      this.dropZone.classList.add("over");
    });
    this.dropZone.addEventListener("dragleave", () => this.dropZone.classList.remove("over"));
    this.dropZone.addEventListener("drop", (event) => {
      event.preventDefault();
      this.dropZone.classList.remove("over");
      this.useBundle(event.dataTransfer.files[0] || null);
    });
  }

  /** Bounds, defaults and allocator choices from the JobCreate schema. */
  configure(schema) {
    const properties = schema.properties || {};
    for (const name of NUMBER_FIELDS) {
      const input = this.form.elements[name];
      const property = properties[name];
      if (!input || !property) continue;
      const bounds = numberSchema(property);
      if (bounds.minimum !== undefined) input.min = bounds.minimum;
      if (bounds.maximum !== undefined) input.max = bounds.maximum;
      const fallback = property.default !== undefined && property.default !== null;
      if (fallback && RULE_DEFAULTS_AS_PLACEHOLDER.includes(name)) input.placeholder = `${property.default} if no rule`;
      else if (fallback) input.value = property.default;
      if (property.description) input.title = property.description;
    }
    // allocator is "one of the kinds, or null" (null: error with the denoiser, variance without).
    const allocator = this.form.elements.allocator;
    const property = properties.allocator || {};
    const kinds = property.enum || ((property.anyOf || []).find((option) => option.enum) || {}).enum || [];
    const automatic = new Option("auto (error; variance without denoise)", "");
    automatic.title = property.description || "";
    allocator.replaceChildren(automatic, ...kinds.map((name) => new Option(name, name)));
    allocator.value = property.default || "";
    if (!this.form.elements.width.value) this.form.elements.width.value = DEFAULT_SIZE;
    if (!this.form.elements.height.value) this.form.elements.height.value = DEFAULT_SIZE;
  }

  setScenes(scenes) {
    this.scenes = scenes;
    this.scene.replaceChildren(...scenes.map((s) => new Option(`${s.name} (${s.width}×${s.height})`, s.name)));
    this.describeScene();
  }

  describeScene() {
    const scene = this.scenes.find((s) => s.name === this.scene.value);
    const integrator = scene && scene.effects && scene.effects.integrator;
    this.description.textContent = scene ? `${scene.description}${integrator ? ` — ${integrator}` : ""}` : "";
    if (!this.bundle) this.params.show({}, "built-in scenes declare no <default> parameters");
  }

  /** The dropped zip's scene parameters, read from its XML in the browser. */
  async readBundleParams() {
    const file = this.bundle;
    if (!file) return;
    try {
      const {xml, defaults} = await zipDefaults(file, this.form.elements.bundle_xml.value.trim());
      if (file !== this.bundle) return;  // another file was chosen meanwhile
      const count = Object.keys(defaults).length;
      this.params.show(defaults, !xml ? "several XMLs: name the one to render to see its parameters"
        : count ? `the <default>s of ${xml}` : `${xml} declares no <default> parameters`);
    } catch (error) {
      this.params.show({}, `parameters not read: ${error.message}`);
    }
  }

  useBundle(file) {
    this.bundle = file;
    if (!file) this.fileInput.value = "";
    this.form.querySelector("#drop-label").textContent = file
      ? `zip: ${file.name} (${(file.size / 1024).toFixed(0)} KiB)` : "…or drop a zipped scene folder here";
    this.dropZone.classList.toggle("chosen", Boolean(file));
    this.scene.disabled = Boolean(file);
    this.form.querySelector("#bundle-clear").hidden = !file;
    this.form.querySelector("#bundle-xml-label").hidden = !file;
    if (file) this.readBundleParams();
    else this.describeScene();
  }

  /** The job spec as JSON: numbers as numbers, blanks left to the server's defaults. */
  spec() {
    const elements = this.form.elements;
    const spec = {};
    for (const name of NUMBER_FIELDS) {
      const text = elements[name].value.trim();
      if (text !== "") spec[name] = Number(text);
    }
    const bad = NUMBER_FIELDS.find((name) => elements[name].validity.badInput);
    if (bad) throw new Error(`${bad}: not a number`);
    if (elements.allocator.value) spec.allocator = elements.allocator.value;  // blank: the server's default
    spec.denoise = elements.denoise.checked;
    const params = this.params.changed();
    if (Object.keys(params).length) spec.params = params;
    return spec;
  }

  async submit() {
    const button = this.form.querySelector("#submit-button");
    button.disabled = true;
    try {
      const spec = this.spec();
      let created;
      if (this.bundle) {
        const xml = this.form.elements.bundle_xml.value.trim();
        created = await api.submitBundle(xml ? {...spec, scene: xml} : spec, this.bundle);
      } else {
        created = await api.submitJSON({...spec, scene: this.scene.value});
      }
      this.onSubmitted(created);
    } catch (error) {
      this.onError(error);
    } finally {
      button.disabled = false;
    }
  }
}
