(function () {
  // One row per task, method (mode), queries of (every query or a city) and k: recall@k and mAP@k
  var ROWS = JSON.parse(document.getElementById("rows").textContent);
  var COLOURS = @COLOURS@, SYMBOLS = @SYMBOLS@, KS = @KS@;
  var FIGURES = [["fig-recall", "Recall@k against k", "recall", "recall@k (%)", 100],
                 ["fig-map", "mAP@k against k", "map", "mAP@k", 1]];
  var FILTERS = [["task", "task"], ["part", "queries of"], ["method", "method"]];
  var TABLE = ["task", "series", "part", "k", "recall", "map", "bytes_per_place", "us_per_query", "n_queries"];

  function values(key) {
    var seen = [];
    ROWS.forEach(function (r) { if (r[key] !== null && seen.indexOf(r[key]) < 0) { seen.push(r[key]); } });
    return seen;
  }
  // "part" has no "every" choice: its rows over every query ("all") and city by city are different figures
  ReportPage.filterBar(FILTERS, function (key) { return key === "part" ? values("part") : ["every"].concat(values(key)); },
                       function (key, opts) { return String(opts[0]); }, function () { draw(); });
  var chosen = ReportPage.chosen, esc = ReportPage.esc;
  function kept(r) {
    return FILTERS.every(function (f) { var v = chosen(f[0]); return v === "every" || String(r[f[0]]) === v; });
  }
  function num(v, digits) { return v === null ? "–" : v.toFixed(digits); }
  function hover(r) {
    return esc(r.series) + "<br>" + esc(r.task) + "<br>queries of " + esc(r.part) + " (" + r.n_queries +
      "), k = " + r.k + "<br>recall@k " + num(r.recall === null ? null : 100 * r.recall, 1) + " %, mAP@k " +
      num(r.map, 3) + "<br>" + num(r.us_per_query, 2) + " µs/query, " + num(r.bytes_per_place, 2) + " B/place";
  }
  var drawn = {};
  ReportPage.places(FIGURES, drawn, "task_rows.csv", ROWS);

  function traces(rows, y, scale) {
    var groups = {}, several = chosen("task") === "every" && values("task").length > 1;
    rows.forEach(function (r) {
      var key = r.series + (several ? " · " + r.task : "");
      (groups[key] = groups[key] || []).push(r);
    });
    return Object.keys(groups).map(function (key) {
      var g = groups[key].slice().sort(function (a, b) { return a.k - b.k; }), r0 = g[0];
      return {x: g.map(function (r) { return r.k; }), y: g.map(function (r) { return r[y] === null ? null : scale * r[y]; }),
              mode: "lines+markers", name: esc(key), text: g.map(hover), hoverinfo: "text",
              marker: {color: COLOURS[r0.method] || "#444", symbol: SYMBOLS[r0.mode] || "circle", size: 7},
              line: {color: COLOURS[r0.method] || "#444", dash: r0.mode === "paper" ? "dash" : r0.mode === "single" ? "dot" : "solid"}};
    });
  }
  function draw() {
    FIGURES.forEach(function (f) {
      var rows = ROWS.filter(kept);
      drawn[f[0]] = rows;
      var layout = {margin: {t: 20}, hovermode: "closest", showlegend: true, legend: {orientation: "v", x: 1.02, y: 1},
                    xaxis: {title: {text: "k (answers read)"}, type: "log", tickvals: KS, ticktext: KS.map(String)},
                    yaxis: {title: {text: f[3]}, range: [0, 1.02 * f[4]]}};
      Plotly.react(f[0], traces(rows, f[2], f[4]), layout, {responsive: true, displaylogo: false});
      ReportPage.table(f[0], rows, TABLE, ["series", "part"]);
      document.getElementById(f[0]).dataset.points = String(rows.length);
    });
    document.body.dataset.drawn = "yes";
  }
  draw();
})();
