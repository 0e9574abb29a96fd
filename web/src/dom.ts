// Tiny DOM helpers: h() builds elements, nothing else is needed for this client.

export type Child = Node | string | number | null | undefined | false | Child[];

export interface Props {
  class?: string;
  testid?: string;
  title?: string;
  style?: string;
  [key: string]: unknown;
}

/** Properties set as DOM properties rather than attributes. */
const PROPERTIES = new Set([
  "value",
  "checked",
  "disabled",
  "type",
  "placeholder",
  "min",
  "max",
  "step",
  "selected",
  "tabIndex",
  "htmlFor",
  "spellcheck",
  "autocomplete",
  "readOnly",
]);

export function h<K extends keyof HTMLElementTagNameMap>(
  tag: K,
  props: Props | null = null,
  ...children: Child[]
): HTMLElementTagNameMap[K] {
  const el = document.createElement(tag);
  if (props) {
    for (const [key, value] of Object.entries(props)) {
      if (value === undefined || value === null || value === false) continue;
      if (key === "class") el.className = String(value);
      else if (key === "testid") el.dataset.testid = String(value);
      else if (key.startsWith("on") && typeof value === "function") {
        el.addEventListener(key.slice(2), value as EventListener);
      } else if (PROPERTIES.has(key)) {
        (el as unknown as Record<string, unknown>)[key] = value;
      } else el.setAttribute(key, value === true ? "" : String(value));
    }
  }
  append(el, children);
  return el;
}

export function append(el: Element, children: Child[]): void {
  for (const child of children) {
    if (child === null || child === undefined || child === false) continue;
    if (Array.isArray(child)) append(el, child);
    else if (child instanceof Node) el.appendChild(child);
    else el.appendChild(document.createTextNode(String(child)));
  }
}

/** Replace all children of ``el``. */
export function replace(el: Element, ...children: Child[]): void {
  el.replaceChildren();
  append(el, children);
}

/** Set the text of ``el`` only when it changes (cheap for 10 Hz readouts). An element
 * that holds one text node keeps it and gets new data: assigning textContent would
 * remove that node and insert a fresh one, a style recalc and a re-attach to layout
 * for every update instead of a text change. */
export function setText(el: Element, text: string): void {
  const only = el.firstChild;
  // (An empty text goes through textContent: it leaves no child, so ``:empty`` matches.)
  if (text && only && only === el.lastChild && only.nodeType === Node.TEXT_NODE) {
    const node = only as Text;
    if (node.data !== text) node.data = text;
  } else if (el.textContent !== text) el.textContent = text;
}

export function toggleClass(el: Element, name: string, on: boolean): void {
  if (el.classList.contains(name) !== on) el.classList.toggle(name, on);
}
