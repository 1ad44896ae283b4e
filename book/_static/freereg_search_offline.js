/* Search excerpts in a book opened from disk (file://).
 *
 * Sphinx's search cuts each result's excerpt from the result's page, which it loads with fetch(); browsers
 * refuse fetch() of file:// URLs, so offline the results came without excerpts. The build writes every
 * page's text into freereg_page_texts.js (book/conf.py, _page_texts); on file:// this script answers those
 * fetches from it. Over http(s) it does nothing. Loaded on the search page only.
 */
(function () {
  "use strict";
  if (window.location.protocol !== "file:") return;
  const realFetch = window.fetch ? window.fetch.bind(window) : null;
  window.fetch = function (resource, init) {
    const texts = window.FREEREG_PAGE_TEXTS || {};
    const root = new URL(document.documentElement.dataset.content_root || "./", window.location.href).href;
    const url = new URL(typeof resource === "string" ? resource : resource.url, window.location.href);
    url.hash = "";
    url.search = "";
    if (url.href.startsWith(root)) {
      const doc = decodeURIComponent(url.href.slice(root.length)).replace(/\.html$/, "");
      if (Object.prototype.hasOwnProperty.call(texts, doc)) {
        return Promise.resolve(new Response(texts[doc], { status: 200, headers: { "Content-Type": "text/html" } }));
      }
    }
    return realFetch ? realFetch(resource, init) : Promise.reject(new TypeError("no fetch in this browser"));
  };
})();
