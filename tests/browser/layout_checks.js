// What a reader sees as broken in one card of the dashboard (tests/browser/test_layout.py evaluates this
// per card): the card's CSS selector in, {overflows, overlaps, emptyFigures, brokenWords, page} out, each a list of
// findings with the text and the pixels that make them (empty lists: nothing broken).
// (a) overflows: a piece of text (each line box of a DOM text node, each SVG <text>) or a control that reaches
//     outside a box it is laid out in: the card itself, a grid cell of one of the card's grids, a box that
//     clips or scrolls (a scrolled-away table column counts: it is not on screen), a figure's own box.
// (b) overlaps: two visible pieces of text whose boxes intersect: DOM line boxes, heat-map cell labels,
//     axis tick labels, titles.
// (c) page: the document wider than the window (a horizontal scroll bar).
// (d) emptyFigures: a figure box (.plot) that takes space while nothing is drawn in it.
// (e) brokenWords: an ordinary word (a number, a unit, a state: up to SHORT_WORD characters) split over two lines
//     between two of its letters or digits: its column is narrower than the word (a grid column of one word, or a
//     few letters, per line).
(cardSelector) => {
  const card = document.querySelector(cardSelector);
  if (!card) throw new Error(`no card ${cardSelector}`);
  const TOLERANCE_PX = 1;  // sub-pixel rounding of line boxes and glyph boxes
  const SHORT_WORD = 24;  // characters: longer tokens (paths, addresses, JSON) may break where they must
  const shown = (el) => el.checkVisibility({ opacityProperty: true, visibilityProperty: true });
  const rectText = (r) => `${Math.round(r.left)}..${Math.round(r.right)} x ${Math.round(r.top)}..${Math.round(r.bottom)}`;
  const clip = (s, n = 60) => (s.length > n ? s.slice(0, n - 1) + "…" : s);

  const describe = (el) => {
    const id = el.id ? `#${el.id}` : "";
    const testid = el.dataset && el.dataset.testid ? `[${el.dataset.testid}]` : "";
    const cls = typeof el.className === "string" && el.className ? `.${el.className.split(" ")[0]}` : "";
    return `${el.tagName.toLowerCase()}${id}${testid}${cls}`;
  };

  // where a word runs onto the next line between two letters or digits (not after "…", "-", "/": the browser's own
  // break opportunities): its index in the word, else 0
  const brokenAt = (node, start, length) => {
    const range = document.createRange();
    const topOf = (k) => {
      range.setStart(node, start + k);
      range.setEnd(node, start + k + 1);
      const r = range.getClientRects()[0];
      return r ? Math.round(r.top) : null;
    };
    const first = topOf(0);
    const word = node.textContent.slice(start, start + length);
    for (let k = 1; k < length; k++) {
      const top = topOf(k);
      if (top !== null && first !== null && top !== first) {
        return /[\p{L}\p{N}]/u.test(word[k - 1]) && /[\p{L}\p{N}]/u.test(word[k]) ? k : 0;
      }
    }
    return 0;
  };

  // the pieces of text and the controls of the card, each with its rect
  const pieces = [];
  const brokenWords = [];
  const svgTexts = new Set();
  const walker = document.createTreeWalker(card, NodeFilter.SHOW_TEXT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    const text = node.textContent.trim();
    const parent = node.parentElement;
    if (!text || !parent || parent.closest("select, script, style, title")) continue;
    if (parent instanceof SVGElement) {
      const el = parent.closest("text");
      if (el && !svgTexts.has(el) && shown(el)) {
        svgTexts.add(el);
        const r = el.getBoundingClientRect();
        if (r.width > 0 && r.height > 0) pieces.push({ el, text: el.textContent.trim(), rect: r });
      }
      continue;
    }
    if (!shown(parent)) continue;
    const range = document.createRange();
    range.selectNodeContents(node);
    for (const r of range.getClientRects()) {
      if (r.width > 0 && r.height > 0) pieces.push({ el: parent, node, text, rect: r });
    }
    for (const word of node.textContent.matchAll(/\S+/g)) {
      if (word[0].length < 2 || word[0].length > SHORT_WORD) continue;
      const at = brokenAt(node, word.index, word[0].length);
      if (at > 0) brokenWords.push({ word: `${word[0].slice(0, at)}|${word[0].slice(at)}`, in: describe(parent), text: clip(text) });
    }
  }
  for (const el of card.querySelectorAll("input, select, textarea, button")) {
    if (!shown(el)) continue;
    const r = el.getBoundingClientRect();
    if (r.width > 0 && r.height > 0) pieces.push({ el, text: `<${el.tagName.toLowerCase()}>`, rect: r, control: true });
  }

  // (a) the boxes a piece is laid out in, from its element up to the card
  const boxes = new Map();
  const boxesOf = (el) => {
    if (boxes.has(el)) return boxes.get(el);
    const out = [];
    for (let a = el; a && a !== card.parentElement; a = a.parentElement) {
      if (a instanceof SVGElement) continue;
      const style = getComputedStyle(a);
      const parentDisplay = a.parentElement ? getComputedStyle(a.parentElement).display : "";
      const why = a === card ? "card"
        : a.classList.contains("js-plotly-plot") ? "figure"
        : /grid/.test(parentDisplay) ? "grid cell"
        : style.overflowX !== "visible" || style.overflowY !== "visible" ? "clipping box" : null;
      if (why) out.push({ box: a, why });
    }
    boxes.set(el, out);
    return out;
  };
  const overflows = [];
  for (const p of pieces) {
    for (const { box, why } of boxesOf(p.el)) {
      const b = box.getBoundingClientRect();
      const out = Math.max(b.left - p.rect.left, p.rect.right - b.right, b.top - p.rect.top, p.rect.bottom - b.bottom);
      if (out > TOLERANCE_PX) {
        overflows.push({ text: clip(p.text), box: `${why} ${describe(box)}`, by_px: Math.round(out),
          piece: rectText(p.rect), box_rect: rectText(b) });
        break;  // the innermost box it leaves says where
      }
    }
  }

  // (b) pairwise, swept along x: pieces sorted by their left edge
  const labels = pieces.filter((p) => !p.control).sort((a, b) => a.rect.left - b.rect.left);
  const overlaps = [];
  for (let i = 0; i < labels.length; i++) {
    const a = labels[i];
    for (let j = i + 1; j < labels.length && labels[j].rect.left < a.rect.right - TOLERANCE_PX; j++) {
      const b = labels[j];
      if (a.node !== undefined && a.node === b.node) continue;  // two lines of one text
      const w = Math.min(a.rect.right, b.rect.right) - Math.max(a.rect.left, b.rect.left);
      const h = Math.min(a.rect.bottom, b.rect.bottom) - Math.max(a.rect.top, b.rect.top);
      if (w > TOLERANCE_PX && h > TOLERANCE_PX) {
        overlaps.push({ a: clip(a.text, 30), b: clip(b.text, 30), where: describe(a.el.closest(".plot") || a.el),
          overlap_px: `${Math.round(w)} x ${Math.round(h)}`, a_rect: rectText(a.rect), b_rect: rectText(b.rect) });
      }
    }
  }

  // (d) a figure box is either drawn or takes no space
  const emptyFigures = [];
  for (const d of card.querySelectorAll(".plot")) {
    const r = d.getBoundingClientRect();
    if (shown(d) && r.height > 0 && !d.querySelector(".main-svg")) {
      emptyFigures.push({ figure: describe(d), size: `${Math.round(r.width)} x ${Math.round(r.height)} px` });
    }
  }

  // (c) the document against the window
  const page = [];
  const width = document.documentElement.scrollWidth;
  if (width > window.innerWidth) page.push({ document_px: width, window_px: window.innerWidth });

  return { overflows, overlaps, emptyFigures, brokenWords, page };
}
