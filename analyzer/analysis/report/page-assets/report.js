/* whiztap's report page: renders the data the report embeds (script#whiztap-data)
   into sortable, filterable tables, uPlot plots and a frame view.  No request
   leaves the page: everything it shows is in the file. */
(function () {
  "use strict";
  const data = JSON.parse(document.getElementById("whiztap-data").textContent);
  const SEVERITY = { error: 3, warning: 2, info: 1, fail: 3, skip: 2, pass: 1 };
  const PAGE_ROWS = 1000;  // rows of a table drawn at first, and added by "show more"

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === null || v === undefined || v === false) continue;
      if (k === "text") node.textContent = v;
      else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
      else node.setAttribute(k, v);
    }
    for (const child of children) if (child !== null && child !== undefined) node.append(child);
    return node;
  }

  // -- tables -------------------------------------------------------------------------------------
  function cell(column, value, row) {
    const td = el("td", { class: "k-" + column.kind });
    if (column.kind === "frames") {
      if (row.f) td.append(el("a", { href: "#frame/" + encodeURIComponent(row.f) + "/" + row.h, class: "frames-link",
                                     text: value || "frames" }));
      else td.textContent = value || "";
    } else if (column.kind === "sev") {
      td.append(el("span", { class: "sev " + value, text: value }));
    } else if (column.kind === "rule" || column.kind === "code") {
      td.append(el("code", { text: value }));
    } else if (column.kind === "num") {
      td.textContent = typeof value === "number" ? value.toLocaleString("en-US", { maximumFractionDigits: 6 }) : value;
    } else {
      td.textContent = value === null || value === undefined ? "" : String(value);
    }
    return td;
  }

  function sortKey(column, value) {
    if (column.kind === "num") return typeof value === "number" ? value : -Infinity;
    if (column.kind === "sev") return SEVERITY[value] || 0;
    return value === null || value === undefined ? "" : String(value).toLowerCase();
  }

  function table(spec) {
    const wrap = el("div", { class: "table", id: "t-" + spec.id });
    const controls = el("div", { class: "controls" });
    const state = { sort: null, desc: false, filters: {}, text: "", limit: PAGE_ROWS };
    const columns = spec.columns;
    for (const key of spec.filters || []) {
      const index = columns.findIndex((c) => c.key === key);
      const values = [...new Set(spec.rows.map((r) => String(r.c[index])))].sort((a, b) =>
        columns[index].kind === "num" ? Number(a) - Number(b) : a.localeCompare(b));
      if (values.length < 2) continue;
      const select = el("select", { "data-filter": key, "aria-label": columns[index].label,
                                    onchange: (e) => { state.filters[index] = e.target.value; draw(); } },
                        el("option", { value: "", text: "every " + columns[index].label }));
      for (const v of values) select.append(el("option", { value: v, text: v }));
      controls.append(select);
    }
    if (spec.rows.length > 1) {
      controls.append(el("input", { type: "search", placeholder: "filter rows", "aria-label": "filter rows",
                                    "data-filter": "text",
                                    oninput: (e) => { state.text = e.target.value.toLowerCase(); draw(); } }));
    }
    const count = el("span", { class: "count" });
    controls.append(count);
    const head = el("tr");
    columns.forEach((column, index) => {
      head.append(el("th", { "data-key": column.key, class: "k-" + column.kind, title: "sort by " + column.label,
                             onclick: () => {
                               state.desc = state.sort === index ? !state.desc : false;
                               state.sort = index;
                               draw();
                             } }, column.label));
    });
    const body = el("tbody");
    const tableNode = el("table", {}, el("thead", {}, head), body);
    wrap.append(controls, tableNode);
    const haystacks = spec.rows.map((r) => r.c.join("\u0001").toLowerCase());

    function draw() {
      let order = spec.rows.map((_, i) => i);
      const filters = Object.entries(state.filters).filter(([, v]) => v !== "");
      if (filters.length || state.text) {
        order = order.filter((i) => filters.every(([c, v]) => String(spec.rows[i].c[c]) === v) &&
                                    (!state.text || haystacks[i].includes(state.text)));
      }
      if (state.sort !== null) {
        const column = columns[state.sort];
        const keys = spec.rows.map((r) => sortKey(column, r.c[state.sort]));
        order.sort((a, b) => (keys[a] < keys[b] ? -1 : keys[a] > keys[b] ? 1 : a - b) * (state.desc ? -1 : 1));
      }
      head.querySelectorAll("th").forEach((th, i) => {
        th.classList.toggle("sorted", i === state.sort);
        th.classList.toggle("desc", i === state.sort && state.desc);
      });
      const fragment = document.createDocumentFragment();
      for (const i of order.slice(0, state.limit)) {
        const row = spec.rows[i];
        const tr = el("tr", { id: row.id || null, "data-row": i });
        columns.forEach((column, c) => tr.append(cell(column, row.c[c], row)));
        fragment.append(tr);
      }
      body.replaceChildren(fragment);
      const n = (x) => x.toLocaleString("en-US");
      const rows = (x) => `${n(x)} ${x === 1 ? "row" : "rows"}`;
      count.textContent = (order.length === spec.rows.length ? rows(spec.rows.length)
                                                             : `${n(order.length)} of ${rows(spec.rows.length)}`)
        + (order.length > state.limit ? ` (the first ${n(state.limit)} shown)` : "");
      more.hidden = order.length <= state.limit;
    }
    // Only the first rows of a long table are drawn (sorting and filtering
    // still go through all of them): 10,000 rows of cells cost seconds to lay out.
    const more = el("button", { class: "more", onclick: () => { state.limit += PAGE_ROWS; draw(); } },
                    `show ${PAGE_ROWS.toLocaleString("en-US")} more`);
    wrap.append(more);
    draw();
    return wrap;
  }

  // -- plots --------------------------------------------------------------------------------------
  function plot(spec, width) {
    const xs = [...new Set(spec.series.flatMap((s) => s.points.map((p) => p[0])))].sort((a, b) => a - b);
    const at = new Map(xs.map((x, i) => [x, i]));
    const columns = [xs];
    for (const s of spec.series) {
      const ys = new Array(xs.length).fill(spec.fill === undefined ? null : spec.fill);
      for (const [x, y] of s.points) ys[at.get(x)] = y;
      columns.push(ys);
    }
    const palette = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                     "#bcbd22", "#17becf"];
    const opts = {
      title: spec.title, width: width, height: 260,
      scales: {
        x: spec.x_log ? { time: false, distr: 3 }
                      : { time: false, range: (u, min, max) => (min === max ? [min - 1, max + 1] : [min, max]) },
        y: { range: (u, min, max) => [0, max > 0 ? max * 1.05 : 1] },
      },
      axes: [{ label: spec.x_label }, { label: spec.y_label, size: 60 }],
      series: [{ label: spec.x_label }].concat(spec.series.map((s, i) => ({
        label: s.label, stroke: s.color || palette[i % palette.length], width: 1.5, spanGaps: true,
        points: { show: s.points.length < 60, size: 5, fill: s.color || palette[i % palette.length] },
        paths: spec.step ? uPlot.paths.stepped({ align: 0 }) : undefined,
      }))),
      cursor: { drag: { x: true, y: false } },
    };
    const holder = el("figure", { class: "plot", "data-plot": spec.id });
    holder.append(el("figcaption", { text: spec.caption || "" }));
    const chart = new uPlot(opts, columns, holder);
    holder.chart = chart;
    return holder;
  }

  // -- the frame view -----------------------------------------------------------------------------
  const dialog = el("dialog", { id: "frame-view" });
  function showFrames(key, hit) {
    const view = data.frames[key];
    dialog.replaceChildren();
    const close = el("button", { class: "close", text: "close", onclick: () => { history.replaceState(null, "", "#"); dialog.close(); } });
    dialog.append(el("header", {}, el("h2", { text: view ? view.title : "frames" }), close));
    if (!view) {
      dialog.append(el("p", { text: "No frames were kept for this row." }));
    } else {
      const around = view.rows.filter((r) => hit < 0 || Math.abs(r.i - hit) <= (data.around || 3));
      const rows = el("tbody");
      for (const r of around) {
        rows.append(el("tr", { class: (r.i === hit ? "hit " : "") + r.dir, "data-index": r.i },
          el("td", { text: String(r.i) }), el("td", { text: r.t.toFixed(6) }), el("td", { text: r.dir }),
          el("td", { text: r.kind }), el("td", {}, el("code", { text: r.text })),
          el("td", { text: r.meaning }), el("td", { text: r.section }),
          el("td", {}, ...r.rules.map((rule) => el("code", { class: "rule", text: rule }))),
          el("td", {}, el("code", { class: "hex", text: r.hex + (r.size > r.hex.length / 3 + 1 ? " …" : "") }))));
      }
      dialog.append(el("table", { class: "frames" }, el("thead", {}, el("tr", {},
        ...["#", "t (s)", "dir", "kind", "bytes", "meaning", "spec section", "rules broken", "hex"].map(
          (h) => el("th", { text: h })))), rows));
      if (view.note) dialog.append(el("p", { class: "note", text: view.note }));
    }
    if (!dialog.open) dialog.showModal();
    const target = dialog.querySelector("tr.hit");
    if (target) target.scrollIntoView({ block: "center" });
  }
  function route() {
    const m = /^#frame\/([^/]*)\/(-?\d+)$/.exec(location.hash);
    if (m) showFrames(decodeURIComponent(m[1]), Number(m[2]));
    else if (dialog.open) dialog.close();
  }

  // -- the page -----------------------------------------------------------------------------------
  function section(spec, width) {
    const node = el("section", { id: spec.id }, el(spec.level === 3 ? "h3" : "h2", { text: spec.title }));
    for (const p of spec.paragraphs || []) node.append(el("p", { class: p.class || null, text: p.text }));
    if (spec.table) node.append(table(spec.table));
    for (const p of spec.plots || []) node.append(plot(p, width));
    for (const sub of spec.sections || []) node.append(section(Object.assign({ level: 3 }, sub), width));
    if (spec.after) for (const p of spec.after) node.append(el("p", { class: p.class || null, text: p.text }));
    return node;
  }

  function render() {
    const main = document.getElementById("report");
    const width = Math.max(600, main.clientWidth - 40);
    main.append(el("h1", { text: data.heading }));
    main.append(el("p", { class: "verdict " + (data.verdict.passed ? "pass" : "fail"), text: data.verdict.text }));
    for (const line of data.lines) main.append(el("p", { class: line.class || null, text: line.text }));
    const nav = el("nav", {});
    for (const s of data.sections) nav.append(el("a", { href: "#" + s.id, text: s.title }));
    main.append(nav);
    for (const s of data.sections) main.append(section(s, width));
    main.append(dialog);
    dialog.addEventListener("close", () => { if (location.hash.startsWith("#frame/")) history.replaceState(null, "", "#"); });
    window.addEventListener("hashchange", route);
    route();
    window.whiztapReady = true;
    document.body.setAttribute("data-ready", "yes");
  }
  render();
})();
