// The TLS suite's checks with amqp091-go: leveret-tls --certs DIR --port PORT
// One JSON line per check: {"name", "outcome"}, outcome "ok" or "refused: ...".
package main

import (
	"crypto/tls"
	"crypto/x509"
	"encoding/json"
	"flag"
	"fmt"
	"os"
	"path/filepath"
	"time"

	amqp "github.com/rabbitmq/amqp091-go"
)

func check(port int, dir, ca, client string, external bool) string {
	pool := x509.NewCertPool()
	pem, err := os.ReadFile(filepath.Join(dir, ca))
	if err != nil {
		return "refused: " + err.Error()
	}
	pool.AppendCertsFromPEM(pem)
	config := &tls.Config{RootCAs: pool, ServerName: "localhost"}
	if client != "" {
		pair, err := tls.LoadX509KeyPair(filepath.Join(dir, client+".pem"), filepath.Join(dir, client+".key"))
		if err != nil {
			return "refused: " + err.Error()
		}
		config.Certificates = []tls.Certificate{pair}
	}
	cfg := amqp.Config{TLSClientConfig: config, Dial: amqp.DefaultDial(20 * time.Second)}
	url := fmt.Sprintf("amqps://guest:guest@localhost:%d/", port)
	if external {
		cfg.SASL = []amqp.Authentication{&amqp.ExternalAuth{}}
		url = fmt.Sprintf("amqps://localhost:%d/", port)
	}
	conn, err := amqp.DialConfig(url, cfg)
	if err != nil {
		return "refused: " + err.Error()
	}
	defer conn.Close()
	ch, err := conn.Channel()
	if err != nil {
		return "refused: " + err.Error()
	}
	q, err := ch.QueueDeclare("", false, false, true, false, nil)
	if err != nil {
		return "refused: " + err.Error()
	}
	if err := ch.Publish("", q.Name, false, false, amqp.Publishing{Body: []byte("tls")}); err != nil {
		return "refused: " + err.Error()
	}
	if err := ch.Qos(1, 0, false); err != nil {
		return "refused: " + err.Error()
	}
	msg, ok, err := ch.Get(q.Name, true)
	if err != nil || !ok || string(msg.Body) != "tls" {
		return fmt.Sprintf("refused: the message did not come back (%v)", err)
	}
	return "ok"
}

func main() {
	dir := flag.String("certs", "", "certificate directory")
	port := flag.Int("port", 0, "TLS port")
	flag.Parse()
	checks := []struct {
		name, ca, client string
		external         bool
	}{
		{"handshake, PLAIN, round trip", "ca.pem", "", false},
		{"mutual TLS, EXTERNAL as robot-7", "ca.pem", "client", true},
		{"server not trusted (rogue CA)", "rogue-ca.pem", "", false},
		{"client certificate from a rogue CA", "ca.pem", "rogue", true},
	}
	out := json.NewEncoder(os.Stdout)
	for _, c := range checks {
		out.Encode(map[string]string{"name": c.name, "outcome": check(*port, *dir, c.ca, c.client, c.external)})
	}
}
