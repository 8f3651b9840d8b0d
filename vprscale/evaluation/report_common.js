// What both report pages share (report_page.js, the frame grid's; task_page.js, MSLS's tasks):
// filters kept in the address, so a view can be bookmarked or sent; values escaped for the
// subset of HTML Plotly reads in hover texts and legend names; tables built node by node, so
// every value is text; each figure's place, with its table and a CSV download of what it drew.
var ReportPage = (function () {
  function esc(v) {
    return String(v).replace(/&/g, "&amp;").replace(/</g, "&lt;").replace(/>/g, "&gt;").replace(/"/g, "&quot;");
  }
  function csv(rows, columnsOf) {
    var cols = Object.keys(rows[0] || columnsOf || {});
    var quote = function (v) { v = v === null ? "" : String(v); return /[",\n]/.test(v) ? '"' + v.replace(/"/g, '""') + '"' : v; };
    return [cols.join(",")].concat(rows.map(function (r) { return cols.map(function (c) { return quote(r[c]); }).join(","); })).join("\n") + "\n";
  }
  function download(name, rows, columnsOf) {
    var a = document.createElement("a");
    a.href = URL.createObjectURL(new Blob([csv(rows, columnsOf)], {type: "text/csv"}));
    a.download = name;
    document.body.appendChild(a); a.click(); a.remove();
  }
  // filters: [key, label]; options(key) the choices of one, opening(key, options) the one it opens on;
  // changed() runs after a choice, once the address holds it
  function filterBar(filters, options, opening, changed) {
    var asked = {};
    location.hash.replace(/^#/, "").split("&").forEach(function (kv) {
      var i = kv.indexOf("=");
      if (i > 0) { asked[decodeURIComponent(kv.slice(0, i))] = decodeURIComponent(kv.slice(i + 1)); }
    });
    var bar = document.getElementById("filters");
    filters.forEach(function (f) {
      var label = document.createElement("label"), sel = document.createElement("select");
      label.textContent = f[1];
      sel.id = "filter-" + f[0];
      var opts = options(f[0]);
      opts.forEach(function (v) { var o = document.createElement("option"); o.value = v; o.textContent = v; sel.appendChild(o); });
      var wanted = asked[f[0]];
      sel.value = wanted !== undefined && opts.map(String).indexOf(wanted) >= 0 ? wanted : opening(f[0], opts);
      sel.addEventListener("change", function () {
        var kv = filters.map(function (g) { return encodeURIComponent(g[0]) + "=" + encodeURIComponent(chosen(g[0])); });
        history.replaceState(null, "", "#" + kv.join("&"));
        changed();
      });
      label.appendChild(sel);
      bar.appendChild(label);
    });
  }
  function chosen(key) { return document.getElementById("filter-" + key).value; }
  // figures: [id, title, …]; drawn[id] the rows a figure last drew, which its button downloads;
  // allName: the file of every row, allRows those rows
  function places(figures, drawn, allName, allRows) {
    var holder = document.getElementById("figures");
    figures.forEach(function (f) {
      var h = document.createElement("h2"); h.textContent = f[1]; holder.appendChild(h);
      var div = document.createElement("div"); div.id = f[0]; div.className = "figure"; holder.appendChild(div);
      var btn = document.createElement("button"); btn.textContent = "Download this figure's table (CSV)";
      btn.id = f[0] + "-csv";
      btn.addEventListener("click", function () { download(f[0] + ".csv", drawn[f[0]] || [], allRows[0]); });
      holder.appendChild(btn);
      var det = document.createElement("details"), sum = document.createElement("summary");
      sum.textContent = "The table behind this figure"; det.appendChild(sum);
      var tab = document.createElement("table"); tab.id = f[0] + "-table"; det.appendChild(tab); holder.appendChild(det);
    });
    document.getElementById("download-all").addEventListener("click", function () { download(allName, allRows); });
  }
  // the table under figure id: the columns cols of rows; each row's data-* attributes from marks
  function table(id, rows, cols, marks) {
    var tab = document.getElementById(id + "-table"), head = document.createElement("tr");
    tab.replaceChildren(head);
    cols.forEach(function (c) { var th = document.createElement("th"); th.textContent = c; head.appendChild(th); });
    rows.forEach(function (r) {
      var tr = document.createElement("tr");
      marks.forEach(function (m) { tr.dataset[m] = r[m]; });
      cols.forEach(function (c) {
        var v = r[c], td = document.createElement("td");
        td.textContent = v === null ? "–" : typeof v === "number" && !Number.isInteger(v) ? v.toPrecision(4) : String(v);
        tr.appendChild(td);
      });
      tab.appendChild(tr);
    });
  }
  return {esc: esc, filterBar: filterBar, chosen: chosen, places: places, table: table};
})();
