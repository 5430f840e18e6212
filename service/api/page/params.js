// Scene parameters: the `<default name value>`s of the scene the form will submit, one field
// each (the same names `renderloop render --param NAME=VALUE` takes). Built-in scenes declare
// none. For a dropped zip they are read here from the zip itself (its central directory, then
// the chosen XML inflated with the browser's DecompressionStream): nothing is uploaded to look.

const EOCD_SIGNATURE = 0x06054b50;  // end of central directory record
const CENTRAL_SIGNATURE = 0x02014b50;
const LOCAL_SIGNATURE = 0x04034b50;
const EOCD_MAX_SEARCH = 22 + 0xffff;  // the record plus the longest zip comment
const MAX_XML_BYTES = 8 * 1024 * 1024;  // a scene file larger than this is not read for its defaults
const STORED = 0;
const DEFLATED = 8;

async function bytes(file, start, end) {
  return new DataView(await file.slice(start, end).arrayBuffer());
}

/** The zip's entries from its central directory: [{name, method, size, offset}]. */
async function zipEntries(file) {
  const tailStart = Math.max(0, file.size - EOCD_MAX_SEARCH);
  const tail = await bytes(file, tailStart, file.size);
  let eocd = -1;
  for (let i = tail.byteLength - 22; i >= 0; i--) {
    if (tail.getUint32(i, true) === EOCD_SIGNATURE) { eocd = i; break; }
  }
  if (eocd < 0) throw new Error("not a zip file");
  const count = tail.getUint16(eocd + 10, true);
  const size = tail.getUint32(eocd + 12, true);
  const offset = tail.getUint32(eocd + 16, true);
  const directory = await bytes(file, offset, offset + size);
  const decoder = new TextDecoder();
  const entries = [];
  for (let at = 0, n = 0; n < count && at + 46 <= directory.byteLength; n++) {
    if (directory.getUint32(at, true) !== CENTRAL_SIGNATURE) break;
    const nameLength = directory.getUint16(at + 28, true);
    const skip = nameLength + directory.getUint16(at + 30, true) + directory.getUint16(at + 32, true);
    const name = decoder.decode(new Uint8Array(directory.buffer, directory.byteOffset + at + 46, nameLength));
    entries.push({name, method: directory.getUint16(at + 10, true), size: directory.getUint32(at + 20, true),
                  offset: directory.getUint32(at + 42, true)});
    at += 46 + skip;
  }
  return entries;
}

async function entryText(file, entry) {
  const local = await bytes(file, entry.offset, entry.offset + 30);
  if (local.getUint32(0, true) !== LOCAL_SIGNATURE) throw new Error(`${entry.name}: damaged zip entry`);
  const start = entry.offset + 30 + local.getUint16(26, true) + local.getUint16(28, true);
  const data = file.slice(start, start + entry.size);
  if (entry.method === STORED) return data.text();
  if (entry.method !== DEFLATED) throw new Error(`${entry.name}: compressed in a way the page cannot read`);
  return new Response(data.stream().pipeThrough(new DecompressionStream("deflate-raw"))).text();
}

/** The XML the server will render: the one named, else the only one nearest the top. */
function entryXML(entries, named) {
  const xmls = entries.filter((e) => e.name.toLowerCase().endsWith(".xml") && !e.name.startsWith("__MACOSX/"));
  if (named) return xmls.find((e) => e.name === named || e.name.endsWith(`/${named}`)) || null;
  const depth = (e) => e.name.split("/").length;
  const top = Math.min(...xmls.map(depth));
  const candidates = xmls.filter((e) => depth(e) === top);
  return candidates.length === 1 ? candidates[0] : null;
}

/** {name: value} of the `<default>`s in a Mitsuba XML document, in order (first one wins). */
export function xmlDefaults(text) {
  const doc = new DOMParser().parseFromString(text, "application/xml");
  if (doc.querySelector("parsererror")) throw new Error("the scene XML does not parse");
  const defaults = {};
  for (const element of doc.getElementsByTagName("default")) {
    const name = element.getAttribute("name");
    if (name && !(name in defaults)) defaults[name] = element.getAttribute("value") ?? "";
  }
  return defaults;
}

/** The defaults of the zip's scene XML, with which XML they came from. */
export async function zipDefaults(file, named) {
  const entry = entryXML(await zipEntries(file), named);
  if (!entry) return {xml: null, defaults: {}};
  if (entry.size > MAX_XML_BYTES) return {xml: entry.name, defaults: {}};
  return {xml: entry.name, defaults: xmlDefaults(await entryText(file, entry))};
}

export class ParamFields {
  constructor(list, note) {
    this.list = list;
    this.note = note;
    this.defaults = {};
  }

  /** One field per parameter, filled with its default; `why` says where they came from. */
  show(defaults, why) {
    this.defaults = defaults;
    this.list.replaceChildren(...Object.entries(defaults).map(([name, value]) => {
      const label = document.createElement("label");
      const input = document.createElement("input");
      input.dataset.param = name;
      input.value = value;
      input.placeholder = value;
      label.append(name, input);
      return label;
    }));
    this.note.textContent = why;
  }

  /** The parameters whose value differs from the scene's default (sent as `params`). */
  changed() {
    const params = {};
    for (const input of this.list.querySelectorAll("input[data-param]")) {
      if (input.value !== this.defaults[input.dataset.param]) params[input.dataset.param] = input.value;
    }
    return params;
  }
}
